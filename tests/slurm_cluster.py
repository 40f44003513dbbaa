"""A throw-away single-node SLURM cluster on localhost, for tests (imported by test modules).

``single_node_cluster(tmpdir)`` writes a munge key and a ``slurm.conf`` into ``tmpdir``, starts
``munged``, ``slurmctld`` and ``slurmd`` in the foreground as child processes (each with its own
socket, ports, pid, state, spool and log files under ``tmpdir``), waits until ``sinfo`` reports
the node idle and yields a :class:`Cluster` whose ``env`` (``SLURM_CONF`` set) makes the client
commands (``sbatch``, ``squeue``, ``scontrol``, …) talk to it. On exit it cancels the jobs left in
its queue and stops exactly the daemons it started (SIGTERM, then SIGKILL), also when the start
fails halfway. The two Unix sockets' folders (munge's socket, slurmd's spool with one socket per
job step) go to a short temporary folder of their own, removed on exit: a socket path may hold
at most 107 bytes, and pytest's ``tmp_path`` under pytest-xdist (``…/popen-gw1/test_…/``) is
longer than that leaves room for. Nothing else outside ``tmpdir`` is written; the system's own
munge/slurm configuration (``/etc/munge``, ``/etc/slurm``) is not read.

Cluster layout, chosen for the 2-core CI machines (no systemd, no cgroups, no database):

- node = this host (``slurmd -C``: its real CPUs and memory), reached on 127.0.0.1;
- one default partition ``debug``;
- ``SelectType=select/cons_tres`` with ``CR_Core``: jobs are packed by cores only, so two
  1-core jobs run at once (as ``--cores 2`` locally); memory requests are checked against the
  node's memory but not reserved or enforced;
- ``ProctrackType=proctrack/linuxproc``, ``TaskPlugin=task/none``: no cgroups;
- no accounting (``accounting_storage/none``, ``jobacct_gather/none``): there is no slurmdbd, so
  ``sacct`` has no job records and job states come from ``squeue`` (``MinJobAge`` keeps finished
  jobs visible there for an hour). The Snakemake SLURM executor then needs
  ``--slurm-status-command squeue``.

Needs root (slurmd runs jobs as their submitting user) and the Debian packages ``munge``,
``slurmctld``, ``slurmd`` and ``slurm-client`` (``scripts/test-deps.sh`` installs them);
:func:`missing_requirements` names what is absent.
"""

from __future__ import annotations

import os
import sys
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path

#: where Debian puts the daemons (often not on a user's PATH), after the folder of the Python
#: running the tests (the jobs call its installed `vlsforest`)
_SEARCH_PATH = os.pathsep.join([os.path.dirname(sys.executable), os.environ.get("PATH", ""), "/usr/sbin", "/sbin",
                                "/usr/bin"])

DAEMONS = ("munged", "slurmctld", "slurmd")
CLIENTS = ("munge", "unmunge", "sbatch", "squeue", "sinfo", "scontrol", "scancel", "srun")

PARTITION = "debug"


def _which(name):
    return shutil.which(name, path=_SEARCH_PATH)


def missing_requirements():
    """Why no cluster can be started here (a skip reason), or None when it can."""
    if not hasattr(os, "geteuid") or sys.platform != "linux":
        return "a local SLURM cluster needs Linux"
    if os.geteuid() != 0:
        return "a local SLURM cluster needs root (slurmd runs jobs as their submitting user)"
    absent = [name for name in DAEMONS + CLIENTS if _which(name) is None]
    if absent:
        return ("SLURM/munge binaries not found: " + ", ".join(absent)
                + " (Debian: apt-get install munge slurmctld slurmd slurm-client; "
                  "see scripts/test-deps.sh)")
    return None


class ClusterError(RuntimeError):
    """The cluster did not come up; the message carries the daemons' log tails."""


@dataclass
class Daemon:
    name: str
    proc: subprocess.Popen
    log: Path
    pid_file: Path | None = None

    @property
    def pid(self):
        return self.proc.pid

    def alive(self):
        return self.proc.poll() is None

    def stop(self, timeout=20.0):
        """SIGTERM, wait, then SIGKILL: this process only, by its pid."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        return self.proc.returncode


@dataclass
class Cluster:
    """A running cluster: ``env`` for the client commands, and what was started."""

    root: Path
    conf: Path
    env: dict
    node: str
    partition: str
    daemons: dict = field(default_factory=dict)

    @property
    def pids(self):
        return {name: d.pid for name, d in self.daemons.items()}

    def run(self, *cmd, check=True, timeout=30):
        """Run a SLURM client command against this cluster; return the process."""
        proc = subprocess.run([_which(cmd[0]) or cmd[0], *map(str, cmd[1:])], env=self.env,
                              cwd=self.root, capture_output=True, text=True, timeout=timeout)
        if check and proc.returncode != 0:
            raise ClusterError(f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n"
                               f"{proc.stdout}{proc.stderr}\n{self.log_tails()}")
        return proc

    def stuck_jobs(self):
        """Pending jobs that SLURM will not start by itself, as (job id, reason): held by a user
        or an admin, or held after a failed launch (e.g. slurmstepd could not create its socket).
        A run that waits for them would wait until its timeout."""
        q = self.run("squeue", "--noheader", "--states=PENDING", "--format", "%i|%r", check=False, timeout=10)
        out = []
        for ln in q.stdout.splitlines():
            jid, _, reason = ln.partition("|")
            if "held" in reason.lower() or "launch failed" in reason.lower():
                out.append((jid.strip(), reason.strip()))
        return out

    def log_tails(self, n=4000):
        parts = []
        for d in self.daemons.values():
            text = d.log.read_text(errors="replace") if d.log.exists() else ""
            parts.append(f"--- {d.name} (pid {d.pid}, rc {d.proc.poll()}) {d.log}:\n{text[-n:]}")
        return "\n".join(parts)


def _free_ports(n):
    socks = []
    try:
        for _ in range(n):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def _node_line(node):
    """This host's hardware as ``slurmd -C`` sees it, as a NodeName line for ``node``."""
    out = subprocess.run([_which("slurmd"), "-C"], capture_output=True, text=True, timeout=30,
                         env={**os.environ, "SLURM_CONF": os.devnull}).stdout
    line = next((ln for ln in out.splitlines() if ln.startswith("NodeName=")), None)
    if line is None:
        raise ClusterError(f"`slurmd -C` printed no NodeName line:\n{out}")
    fields = [f for f in line.split()[1:] if not f.startswith("UpTime")]
    return f"NodeName={node} NodeAddr=127.0.0.1 NodeHostname={node} " + " ".join(fields)


#: the longest Unix socket path Linux accepts (sun_path holds 108 bytes with the final NUL)
MAX_SOCKET_PATH = 107

#: slurmd's socket of a job step: ``{SlurmdSpoolDir}/{node}_{jobid}.{stepid}``; the batch step's
#: id is 4294967291, the job ids of a test run stay far below 10**7
_STEP_SOCKET = "{node}_9999999.4294967291"


def write_config(root, node, sockets):
    """Write ``slurm.conf`` and the munge key under ``root``; return the slurm.conf path.

    ``sockets`` is the (short) folder of munge's socket and slurmd's spool.
    """
    root, sockets = Path(root), Path(sockets)
    for sub in ("munge", "state", "log"):
        (root / sub).mkdir(parents=True, exist_ok=True)
        os.chmod(root / sub, 0o700)
    spool = sockets / "spool" / "slurmd-%n"
    longest = max(len(str(sockets / "munge.socket")),
                  len(str(spool).replace("%n", node)) + 1 + len(_STEP_SOCKET.format(node=node)))
    if longest > MAX_SOCKET_PATH:
        raise ClusterError(f"socket paths under {sockets} would be {longest} bytes long "
                           f"(Linux allows {MAX_SOCKET_PATH}); use a shorter folder")
    (sockets / "spool").mkdir(parents=True, exist_ok=True)
    os.chmod(sockets / "spool", 0o700)
    key = root / "munge" / "munge.key"
    key.write_bytes(os.urandom(1024))
    os.chmod(key, 0o400)
    ctld_port, slurmd_port = _free_ports(2)
    conf = root / "slurm.conf"
    conf.write_text(f"""\
# single-node test cluster on localhost (written by tests/slurm_cluster.py)
ClusterName=vlsforest-test
SlurmctldHost={node}(127.0.0.1)
SlurmctldPort={ctld_port}
SlurmdPort={slurmd_port}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={sockets / "munge.socket"}
StateSaveLocation={root / "state"}
SlurmdSpoolDir={spool}
SlurmctldPidFile={root / "slurmctld.pid"}
SlurmdPidFile={root / "slurmd.pid"}
SlurmctldLogFile={root / "log" / "slurmctld.log"}
SlurmdLogFile={root / "log" / "slurmd.log"}
SlurmctldDebug=info
SlurmdDebug=info
MpiDefault=none
MailProg=/bin/true
SwitchType=switch/none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
MinJobAge=3600
KillWait=5
InactiveLimit=0
SlurmdTimeout=300
{_node_line(node)} State=UNKNOWN
PartitionName={PARTITION} Nodes={node} Default=YES MaxTime=INFINITE State=UP
""")
    return conf


def _srun_shim(root, conf):
    """A folder with an ``srun`` that finds this cluster's slurm.conf; return the folder.

    Inside a batch job, snakemake-executor-plugin-slurm-jobstep (0.6.1) starts the rule with
    ``srun`` in an environment stripped of every ``SLURM_*`` variable except the job's ids, so
    ``SLURM_CONF`` is lost and srun would look for /etc/slurm/slurm.conf (upstream:
    snakemake/snakemake-executor-plugin-slurm#164). Real clusters keep slurm.conf at the
    default path or run configless; this throw-away cluster must not touch /etc or /run, so the
    jobs get SLURM_CONF back through this wrapper, which is first on the PATH they inherit.
    """
    bindir = Path(root) / "bin"
    bindir.mkdir(exist_ok=True)
    shim = bindir / "srun"
    shim.write_text(f'#!/bin/sh\n: "${{SLURM_CONF:={conf}}}"\nexport SLURM_CONF\n'
                    f'exec {_which("srun")} "$@"\n')
    shim.chmod(0o755)
    return bindir


def _wait(predicate, timeout, what, cluster, poll=0.5):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        for d in cluster.daemons.values():
            if not d.alive():
                raise ClusterError(f"{d.name} exited (rc {d.proc.returncode}) while waiting "
                                   f"for {what}\n{cluster.log_tails()}")
        if predicate():
            return
        time.sleep(poll)
    raise ClusterError(f"timed out after {timeout:.0f} s waiting for {what}\n{cluster.log_tails()}")


def _start(cluster, name, args, pid_file=None):
    log = cluster.root / "log" / f"{name}.stdout"
    with open(log, "ab") as fh:
        proc = subprocess.Popen([_which(name), *map(str, args)], stdin=subprocess.DEVNULL,
                                stdout=fh, stderr=subprocess.STDOUT, env=cluster.env,
                                cwd=cluster.root)
    cluster.daemons[name] = Daemon(name, proc, log, pid_file)
    return cluster.daemons[name]


def _node_state(cluster):
    proc = cluster.run("sinfo", "--noheader", "--node", cluster.node, "--format", "%T",
                       check=False, timeout=10)
    return proc.stdout.strip().lower() if proc.returncode == 0 else ""


def _shutdown(cluster, timeout):
    """Cancel this cluster's jobs, then stop its daemons in reverse start order."""
    if "slurmctld" in cluster.daemons and cluster.daemons["slurmctld"].alive():
        try:
            cluster.run("scancel", "--full", "--user", "root", check=False, timeout=10)
            t_end = time.monotonic() + timeout
            while time.monotonic() < t_end:
                q = cluster.run("squeue", "--noheader", "--format", "%i", check=False, timeout=10)
                if q.returncode != 0 or not q.stdout.strip():
                    break
                time.sleep(0.5)
        except (subprocess.TimeoutExpired, OSError):
            pass
    for name in reversed(list(cluster.daemons)):
        cluster.daemons[name].stop()


@contextmanager
def single_node_cluster(tmpdir, *, start_timeout=60.0, stop_timeout=30.0):
    """Start munged, slurmctld and slurmd on this host with state under ``tmpdir``; yield a
    :class:`Cluster`; stop them (and only them) on exit, whatever happened."""
    reason = missing_requirements()
    if reason:
        raise ClusterError(reason)
    root = Path(tmpdir)
    root.mkdir(parents=True, exist_ok=True)
    node = socket.gethostname().split(".")[0]
    with ExitStack() as stack:
        sockets = Path(tempfile.mkdtemp(prefix="vlsf-slurm-"))
        stack.callback(shutil.rmtree, sockets, ignore_errors=True)  # last: after the daemons stopped
        conf = write_config(root, node, sockets)
        env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "SBATCH_", "SRUN_"))}
        env["SLURM_CONF"] = str(conf)
        env["PATH"] = os.pathsep.join([str(_srun_shim(root, conf)), _SEARCH_PATH])
        cluster = Cluster(root, conf, env, node, PARTITION)
        munge_socket = sockets / "munge.socket"
        stack.callback(_shutdown, cluster, stop_timeout)
        _start(cluster, "munged", [
            "--foreground", "--force",
            f"--key-file={root / 'munge' / 'munge.key'}",
            f"--socket={munge_socket}",
            f"--pid-file={root / 'munge' / 'munged.pid'}",
            f"--log-file={root / 'log' / 'munged.log'}",
            f"--seed-file={root / 'munge' / 'munged.seed'}",
        ], root / "munge" / "munged.pid")

        def munge_works():
            if not munge_socket.exists():
                return False
            cred = subprocess.run([_which("munge"), "-n", "-S", str(munge_socket)],
                                  capture_output=True, timeout=10)
            if cred.returncode != 0:
                return False
            return subprocess.run([_which("unmunge"), "-S", str(munge_socket)], input=cred.stdout,
                                  capture_output=True, timeout=10).returncode == 0

        _wait(munge_works, start_timeout, "munged to answer", cluster)
        _start(cluster, "slurmctld", ["-D", "-f", conf], root / "slurmctld.pid")
        _wait(lambda: "UP" in cluster.run("scontrol", "ping", check=False, timeout=10).stdout,
              start_timeout, "slurmctld to answer `scontrol ping`", cluster)
        _start(cluster, "slurmd", ["-D", "-f", conf, "-N", node], root / "slurmd.pid")
        _wait(lambda: _node_state(cluster) == "idle", start_timeout,
              f"node {node} to be idle in sinfo", cluster)
        yield cluster


def pid_alive(pid):
    """Whether a process with this pid exists (and is not a zombie)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"
