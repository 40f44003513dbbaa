"""The quick workflow on a real (single-node, localhost) SLURM cluster through profiles/slurm.

A throw-away cluster (munged, slurmctld, slurmd; see tests/slurm_cluster.py) is started in a
temporary folder; Snakemake runs ``config/quick.yaml`` with ``--workflow-profile profiles/slurm``
and the SLURM executor, so every job goes through ``sbatch`` and runs under ``slurmd``. The
results must be byte-identical to the local run (``quick_run`` fixture) except for the wall-clock
timings, and the daemons must be gone afterwards.

Needs root and the Debian packages munge/slurmctld/slurmd/slurm-client (scripts/test-deps.sh);
skipped with the reason otherwise. The Snakemake SLURM plugins are pinned dependencies
(envs/requirements.txt): imported plainly, so a broken install fails. About 5 min on 2 cores on top
of the shared quick run (measured: 530 s, against 276 s for the local run, with the
machine also busy elsewhere; about twice the local run: every job starts Snakemake twice and
the plugin polls squeue with a growing interval).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest
import snakemake_executor_plugin_slurm  # noqa: F401  (pinned in envs/requirements.txt)
import snakemake_executor_plugin_slurm_jobstep  # noqa: F401  (pinned: the jobs' step executor)
import yaml

from slurm_cluster import missing_requirements, pid_alive, single_node_cluster
from wfrun import QUICK, REPO, snakemake_command

SLURM_PROFILE = REPO / "profiles" / "slurm"

#: wall-clock timings differ between runs by nature (as in test_workflow's determinism test)
NONDETERMINISTIC = ("timing.json", "sim_times.csv", "table5.csv")

_REASON = missing_requirements()
pytestmark = pytest.mark.skipif(_REASON is not None, reason=_REASON or "")


def _result_files(workdir):
    return {str(p.relative_to(workdir)) for p in (Path(workdir) / "results").rglob("*")
            if p.is_file() and p.name not in NONDETERMINISTIC}


def _steps_done(text):
    """Total job count of a finished Snakemake run ("N of N steps (100%) done")."""
    done = re.findall(r"(\d+) of (\d+) steps \(100%\) done", text)
    assert done, text[-3000:]
    return int(done[-1][1])


def _snakemake_watched(cluster, logdir, *args, cwd, timeout, poll=5.0):
    """Run the Snakemake CLI against ``cluster`` (like ``snakemake_cli``), but stop it and fail
    at once when one of its jobs is stuck in the queue (:meth:`Cluster.stuck_jobs`) instead of
    waiting out ``timeout``; the failure carries the daemons' log tails."""
    cmd = snakemake_command(*args)
    out_path, err_path = Path(logdir) / "snakemake.stdout", Path(logdir) / "snakemake.stderr"
    with open(out_path, "w") as out, open(err_path, "w") as err:
        proc = subprocess.Popen(cmd, cwd=cwd, stdout=out, stderr=err, env=cluster.env,
                                start_new_session=True)
        t_end = time.monotonic() + timeout
        try:
            while proc.poll() is None:
                stuck = cluster.stuck_jobs()
                if stuck or time.monotonic() > t_end:
                    why = f"jobs stuck in the queue: {stuck}" if stuck else f"timed out after {timeout} s"
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
                    pytest.fail(f"Snakemake stopped, {why}\n{err_path.read_text()[-3000:]}\n"
                                f"{cluster.log_tails()}")
                time.sleep(poll)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    return subprocess.CompletedProcess(cmd, proc.returncode, out_path.read_text(), err_path.read_text())


@pytest.mark.early  # one of the longest tests: started first (tests/conftest.py)
def test_quick_run_through_slurm_matches_the_local_run(quick_run, tmp_path):
    local, local_proc, local_seconds = quick_run
    profile = yaml.safe_load((SLURM_PROFILE / "profile.yaml").read_text())
    assert profile["executor"] == "slurm"
    workdir = tmp_path / "work"
    workdir.mkdir()

    with single_node_cluster(tmp_path / "cluster") as cluster:
        daemons = dict(cluster.pids)
        assert set(daemons) == {"munged", "slurmctld", "slurmd"}
        assert all(pid_alive(pid) for pid in daemons.values())
        cpus = int(cluster.run("sinfo", "--noheader", "--format", "%c").stdout.split()[0])
        t0 = time.perf_counter()
        proc = _snakemake_watched(
            cluster, tmp_path,
            "--workflow-profile", SLURM_PROFILE,
            "--configfile", QUICK,
            "--executor", "slurm",
            # no conda here: env-modules switches the profile's conda off (no rule uses
            # envmodules:), so the jobs run in this venv, as the local run does
            "--sdm", "env-modules",
            # the profile's threads (simulate: 8, synth_plot: 16) exceed this node's CPUs; SLURM
            # would keep such jobs pending forever
            "--max-threads", cpus,
            # no slurmdbd: sacct has no records, squeue knows the jobs for MinJobAge (1 h)
            "--slurm-status-command", "squeue",
            # the plugin polls after this many seconds, then 10 s longer each time nothing
            # finished (reset on a finish); the quick run's jobs take ~5-20 s each
            "--slurm-init-seconds-before-status-checks", 3,
            "--slurm-keep-successful-logs",
            cwd=workdir, timeout=900)
        seconds = time.perf_counter() - t0
        out = proc.stdout + proc.stderr
        assert proc.returncode == 0, out[-5000:] + "\n" + cluster.log_tails()
        run_id = re.search(r"SLURM run ID: (\S+)", out).group(1)
        jobs = [ln.split("|") for ln in cluster.run(
            "squeue", "--noheader", "--states=all", "--name", run_id,
            "--format", "%i|%T|%N|%C|%k|%S|%e").stdout.split()]
    print(f"\nquick run through SLURM: {seconds:.1f} s ({len(jobs)} sbatch jobs; "
          f"local run {local_seconds:.1f} s)")

    # the daemons started for the test are gone
    assert not any(pid_alive(pid) for pid in daemons.values()), daemons
    assert all(d.proc.returncode is not None for d in cluster.daemons.values())

    # every job of the DAG went through sbatch and completed on the node; the profile was used
    assert "profiles/slurm" in out
    submitted = re.findall(r"has been submitted with SLURM jobid (\d+)", out)
    n_steps = _steps_done(out)
    assert n_steps == _steps_done(local_proc.stdout + local_proc.stderr)
    local_rules = re.findall(r"^localrule (\w+):", out, flags=re.M)
    assert local_rules == ["all"]  # only the input-only target rule runs on the submit host
    assert len(set(submitted)) == len(submitted) == n_steps - 1 >= 10
    assert {j[0] for j in jobs} == set(submitted)
    assert all(state == "COMPLETED" and node == cluster.node for _, state, node, *_ in jobs), jobs
    assert any(comment.startswith("rule_simulate") for *_, comment, _, _ in jobs), jobs
    slurm_logs = {p.stem for p in (workdir / ".snakemake" / "slurm_logs").rglob("*.log")}
    assert slurm_logs == set(submitted)
    # SLURM's own limits came from the rules and the profile: the plot's synthesis asked for
    # every CPU (16, capped by --max-threads)
    synth = [j for j in jobs if j[4].startswith("rule_synth_plot")]
    assert len(synth) == 1 and int(synth[0][3]) == cpus
    # select/cons_tres packed two 1-core jobs onto the 2 CPUs at once at least once
    spans = sorted((s, e) for _, _, _, c, _, s, e in jobs if int(c) == 1)
    assert any(b[0] < a[1] for a, b in zip(spans, spans[1:])), spans

    # the same results as the local run, byte for byte (timings aside)
    files = _result_files(local)
    assert files == _result_files(workdir)
    assert any(f.endswith("sim.laz") for f in files) and any(f.endswith(".png") for f in files)
    differ = [f for f in sorted(files) if (local / f).read_bytes() != (workdir / f).read_bytes()]
    assert not differ, differ


def test_a_failed_start_stops_the_daemons_already_started(tmp_path, monkeypatch):
    """slurmctld dies at start (here: /bin/false in its place): the error names it and the
    munged started before it is stopped."""
    import slurm_cluster

    which, started = slurm_cluster._which, []
    monkeypatch.setattr(slurm_cluster, "_which",
                        lambda name: "/bin/false" if name == "slurmctld" else which(name))
    start = slurm_cluster._start
    monkeypatch.setattr(slurm_cluster, "_start", lambda *a, **k: started.append(start(*a, **k))
                        or started[-1])
    mkdtemp, sockets = slurm_cluster.tempfile.mkdtemp, []
    monkeypatch.setattr(slurm_cluster.tempfile, "mkdtemp",
                        lambda **k: sockets.append(mkdtemp(**k)) or sockets[-1])
    with pytest.raises(slurm_cluster.ClusterError, match="slurmctld exited"):
        with single_node_cluster(tmp_path / "cluster", start_timeout=30):
            pytest.fail("the cluster came up without slurmctld")
    assert [d.name for d in started] == ["munged", "slurmctld"]
    assert all(d.proc.returncode is not None and not pid_alive(d.pid) for d in started)
    # munge's socket lived in the short sockets folder, which is gone with the daemons
    assert len(sockets) == 1 and not Path(sockets[0]).exists()


def test_socket_paths_too_long_for_linux_are_refused_before_any_daemon_starts(tmp_path):
    import slurm_cluster

    deep = tmp_path / ("d" * 90)
    with pytest.raises(slurm_cluster.ClusterError, match="Linux allows 107"):
        slurm_cluster.write_config(tmp_path / "cluster", "node", deep)
    assert not (deep / "spool").exists()


def test_a_held_job_is_reported_stuck_and_runs_once_released(tmp_path):
    """What the SLURM run's watcher stops on: a held job is stuck (it would never start), the
    same job released is not, and then runs to completion."""
    with single_node_cluster(tmp_path / "cluster", start_timeout=30) as cluster:
        assert cluster.stuck_jobs() == []
        jid = cluster.run("sbatch", "--parsable", "--hold", "--output", tmp_path / "job.out",
                          "--wrap", "echo ran").stdout.strip().split(";")[0]
        stuck = cluster.stuck_jobs()
        assert [j for j, _ in stuck] == [jid] and "held" in stuck[0][1].lower(), stuck
        cluster.run("scontrol", "release", jid)
        t_end = time.monotonic() + 60
        while time.monotonic() < t_end and not (tmp_path / "job.out").is_file():
            assert cluster.stuck_jobs() == []
            time.sleep(0.5)
        t_end = time.monotonic() + 30
        while time.monotonic() < t_end and (tmp_path / "job.out").read_text().strip() != "ran":
            time.sleep(0.5)
        assert (tmp_path / "job.out").read_text().strip() == "ran"
