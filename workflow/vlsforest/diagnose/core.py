"""The diagnosis: locate a sim-vs-real mismatch, attribute it, fit the winner, check on held-out trees.

Steps (see docs/diagnosis.md):

1. **Locate** — per tree, real minus simulated observables (:mod:`.features`); per observable the
   mean residual with a bootstrap CI, Wilcoxon p and Benjamini–Hochberg q; a global sign-flip
   permutation test. ``significant_mismatch`` = global p < α or any q < α.
2. **Attribute** — each candidate's signature ``J_k`` = mean change of the observables when its
   parameter moves by a reference step (common random numbers: same pulses, same seed);
   projection of the mean residual on ``J_k`` (weights: 1 / mean square residual per
   observable) gives an amplitude and an explained fraction; physically impossible signs score 0;
   a penalty per parameter ranks simpler candidates first at equal fit. The leader must explain
   more than a signature unrelated to the residual would by chance (the 1 − α/K quantile of
   Beta(½, (m − 1)/2) for m observables and K candidates) and pass a matched-filter test
   across trees (Bonferroni over candidates). Members of a declared
   group (or signatures with |cos| > 0.9) that score within 0.1 of each other tie; the tie is
   broken on the group's separating observables and the report names them — or, when those do
   not separate the members either (explained fractions within 0.05), the report says so and the
   simplest member is fitted on behalf of the group.
3. **Model** — the winner's parameter(s) are fitted on a grid (one simulation per grid point,
   shared by all folds; several parameters by coordinate search; the ellipse along its aspect
   ratio at the solid angle of the beam simulated so far): each observable whose
   mean residual changes sign along the grid votes for its crossing, and the weighted median of
   the votes, interpolated between neighbouring votes, is the estimate
   (:func:`.stats.robust_fit`; observables dominated by errors the
   candidate cannot remove do not vote); k-fold across trees: each fold's value is fitted on
   the other trees and simulated for the held-out ones. The effect is accepted when the held-out per-tree error drops
   significantly (one-sided paired Wilcoxon); observables that get significantly worse (Holm)
   are named in the report and the verdict. For an accepted candidate whose simulation is one
   draw of a random process with few independent samples over a plot (trajectory noise:
   :attr:`.library.Candidate.realisations`), further draws are simulated at the fitted value and
   each is fitted as if it were the recording: the estimate is matched with the draws' mean
   amplitude instead of draw 0's alone (the simulation's draw then adds little scatter), and
   the scatter that remains — the recording's own draw's — widens the CI. So do the voters'
   own systematic errors: the larger of their disagreement beyond their sampling variances
   (:func:`.stats.crossing_votes`) and the bias allowance, which gives each voter a bias as
   large, in across-tree SDs, as those the fit leaves in the observables it did not use
   (:func:`.stats.bias_scale`; it covers a fit that rests on one observable, whose bias no
   disagreement shows); ``ci95_trees`` is the bootstrap over trees alone.
   Then a second effect is sought the same way on top of the first.
4. **Report** — the JSON contract of the issue (``significant_mismatch``, ``mismatches``,
   ``effects``, ``accepted``) plus the verdict in words, the group/tie-breaker reasoning, the
   fitted values with bootstrap CIs, the minimum detectable effect per candidate and the cost;
   ``model`` (the accepted candidates' values, as simulated: for a random process draw 0's
   fit, ``realisation_scatter.draw0_fit``, while its effect's ``parameters`` hold the estimate
   matched with the mean of the draws) and ``beam_fwhm_mrad`` (the beam
   they make, major and minor divergence at FWHM).
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from vlsforest.diagnose import library as lib
from vlsforest.diagnose import stats as st
from vlsforest.diagnose.features import (FEATURES, GROUND_PAD_M, STRATUM, cloud_arrays, tree_features, tree_labeller,
                                         tree_table)
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.yamlfile import read_yaml

ALPHA = 0.05
PENALTY = 0.05          # explained-fraction penalty per parameter
TIE_MARGIN = 0.10       # scores closer than this tie within a group
TIE_RESOLVE = 0.05      # a tie is broken only if the separating observables differ by this much
DOMINANT_VOTE = 0.5     # a fit whose one observable carries more of the weight "rests on" it (reported)
MIN_EV = 0.05           # a candidate must explain at least this share of the mean residual
#                         (the reconstruction error of the voxel model is always there beside it)
MAX_EFFECTS = 2         # effects accepted one after another at most (stages of the attribution)
#: default of a plot's ``margin`` (m): the diagnosis traces the pulses that enter the trees'
#: observed region ± this; the workflow's ``diagnosis.region_margin_m`` falls back to it too
REGION_MARGIN_M = 1.0


@dataclass
class PlotInput:
    """What the diagnosis needs of one plot."""

    name: str
    real: Path
    scene: Path
    survey: Path
    segment: Path
    radius: float
    margin: float = REGION_MARGIN_M


@dataclass
class Setup:
    """A diagnosis set-up: plots, scenario, candidates and settings (see :func:`load_setup`)."""

    scenario: str
    plots: list
    candidates: list = field(default_factory=lambda: list(lib.CANDIDATES))
    folds: int = 3
    seed: int = 0
    workers: int = 2
    grid: int = 7
    #: whether ``candidates`` was given (else: the whole library, less what the scenes cannot model)
    candidates_given: bool = False
    #: sub-ray rings of the diagnosis' own simulations (None: the survey's). Footprint fits are
    #: biased when the simulation samples the beam more coarsely than the real beam is (fewer
    #: sub-rays split fewer echoes, so a wider beam is fitted); see docs/diagnosis.md
    beam_sample_quality: int | None = None
    #: further draws of a random candidate's process simulated at its fitted value, whose
    #: scatter widens its CI (one trace each; 0: no draws, the CI holds the trees' bootstrap and
    #: the observables' disagreement only)
    realisations: int = 3
    #: benchmarks only: the hidden truth as candidate values; the report then also gives the
    #: error of a simulation told these values (the "recoverable" error's reference)
    oracle: dict | None = None


def load_setup(path, real_dir=None, scenario=None) -> Setup:
    """Read a sim-config YAML (or take the same as a mapping).

    Format::

        scenario: uls                 # als | uls (the CLI's --scenario overrides it)
        recording: uls                # file name of the real recording per plot (default: scenario)
        seed: 0
        folds: 3                      # k-fold across trees
        candidates: [range_noise, …]  # default: the whole library
        beam_sample_quality: 4        # sub-ray rings of the diagnosis' simulations (default: the
                                      # survey's); finer than the study's for footprint fits
        realisations: 3               # further draws of an accepted trajectory-noise fit's process
                                      # (one trace each) whose scatter widens its CI; 0: none
        plots:
          Q1:
            real: …/Q1/uls.laz        # default: <--real DIR>/<plot>/<recording>.laz
            scene: results/Q1/scaled/scene/scene.yaml
            survey: results/Q1/surveys/uls.yaml
            segment: results/Q1/segment     # segmentation folder (trees.csv, trees/*.laz)
            radius: 0.3               # extraction radius around the TLS tree points (m)
            margin: 1                 # pulses are traced where they enter the observed region
                                      # (the trees' points ± radius and the ground columns under
                                      # their crowns) ± this (m; default 1,
                                      # :data:`REGION_MARGIN_M`)

    Relative paths are taken from the current directory.
    """
    if isinstance(path, dict):
        d, path = path, "sim-config"
    else:
        path = Path(path)
        d = read_yaml(path, "sim-config", empty={})
    if not isinstance(d, dict):
        raise ConfigError(f"{path}: must be a mapping")
    known = {"scenario", "recording", "seed", "folds", "candidates", "plots", "workers", "grid",
             "beam_sample_quality", "realisations"}
    for k in d:
        if k not in known:
            raise ConfigError(f"{path}: unknown key {k!r} (known: {', '.join(sorted(known))})")
    scen = scenario or d.get("scenario")
    if scen not in ("als", "uls"):
        raise ConfigError(f"{path}: scenario must be als or uls, got {scen!r}")
    rec = d.get("recording", scen)
    plots = d.get("plots")
    if not isinstance(plots, dict) or not plots:
        raise ConfigError(f"{path}: plots must be a non-empty mapping of plot name → inputs")
    out = []
    for name, p in plots.items():
        if not isinstance(p, dict):
            raise ConfigError(f"{path}: plots.{name} must be a mapping")
        for k in ("scene", "survey", "segment", "radius"):
            if k not in p:
                raise ConfigError(f"{path}: plots.{name}.{k} is missing")
        real = p.get("real")
        if real is None:
            if real_dir is None:
                raise ConfigError(f"{path}: plots.{name}.real is missing and no --real DIR was given")
            real = Path(real_dir) / str(name) / f"{rec}.laz"
        r = p["radius"]
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not r > 0:
            raise ConfigError(f"{path}: plots.{name}.radius must be > 0, got {r!r}")
        m = p.get("margin", REGION_MARGIN_M)
        if isinstance(m, bool) or not isinstance(m, (int, float)) or not m >= 0:
            raise ConfigError(f"{path}: plots.{name}.margin must be a number ≥ 0 (m), got {m!r}")
        out.append(PlotInput(str(name), Path(real), Path(p["scene"]), Path(p["survey"]), Path(p["segment"]),
                             float(r), float(m)))
    cands = d.get("candidates") or list(lib.CANDIDATES)
    lib.select(cands)
    folds = d.get("folds", 3)
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 2:
        raise ConfigError(f"{path}: folds must be an integer ≥ 2, got {folds!r}")
    q = d.get("beam_sample_quality")
    if q is not None and (isinstance(q, bool) or not isinstance(q, int) or q < 1):
        raise ConfigError(f"{path}: beam_sample_quality must be an integer ≥ 1, got {q!r}")
    nr = d.get("realisations", 3)
    if isinstance(nr, bool) or not isinstance(nr, int) or nr < 0:
        raise ConfigError(f"{path}: realisations must be an integer ≥ 0, got {nr!r}")
    workers = d.get("workers", 2)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"{path}: workers must be an integer ≥ 1, got {workers!r}")
    return Setup(scen, out, list(cands), folds, int(d.get("seed", 0)), workers,
                 int(d.get("grid", 7)), candidates_given=bool(d.get("candidates")),
                 beam_sample_quality=q, realisations=nr)


# ------------------------------------------------------------------------------------ simulation
def _observed_region(tree_points: dict, trees: pd.DataFrame, radius: float, margin: float) -> list:
    """The horizontal box (xmin, ymin, xmax, ymax) whose returns the observables read, ± ``margin``.

    The trees' returns lie within ``radius`` of their TLS points; the ground observables read
    the columns of crown radius + :data:`~vlsforest.diagnose.features.GROUND_PAD_M` around the
    stems. A pulse whose beam never enters the box (from the ground to the scene's top) leaves
    no return in it, so the diagnosis traces only the pulses that enter it: the observables are
    those of the whole survey, at the cost of the pulses that matter.
    """
    allp = np.concatenate([np.asarray(v)[:, :2] for v in tree_points.values()])
    lo, hi = allp.min(axis=0) - radius, allp.max(axis=0) + radius
    if len(trees):
        reach = trees["crown_radius"].to_numpy(float) + GROUND_PAD_M
        xy = trees[["x", "y"]].to_numpy(float)
        lo = np.minimum(lo, (xy - reach[:, None]).min(axis=0))
        hi = np.maximum(hi, (xy + reach[:, None]).max(axis=0))
    return [float(lo[0] - margin), float(lo[1] - margin), float(hi[0] + margin), float(hi[1] + margin)]


def _trace_part(assign: dict) -> dict:
    """The candidates of ``assign`` that need a new ray trace (the rest re-renders stored hits)."""
    return {k: v for k, v in assign.items() if lib.CANDIDATES[k].render == "trace"}


def _release_freed_memory():
    """Give freed heap pages back to the system (glibc only; elsewhere nothing happens).

    A trace gathers its hits from ≈ 20 000-pulse blocks of a few MB each; glibc serves such
    sizes from its heap once its adaptive mmap threshold has grown, and keeps the freed pages
    mapped after the blocks are joined, so the process would hold them for the rest of the run.
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        trim = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        trim = None
    if trim is not None:
        trim(0)


def _save_trace(folder: Path, trace: tuple) -> None:
    """Write a trace (pulses, hits) as one ``.npy`` file per array (key order kept)."""
    folder.mkdir(parents=True)
    order = {}
    for name, arrays in zip(("pulses", "hits"), trace):
        order[name] = list(arrays)
        for k, v in arrays.items():
            np.save(folder / f"{name}.{k}.npy", v, allow_pickle=False)
    (folder / "order.json").write_text(json.dumps(order))


def _load_trace(folder: Path) -> tuple:
    """Read back what :func:`_save_trace` wrote: the same arrays, dtypes and key order."""
    order = json.loads((folder / "order.json").read_text())
    return tuple({k: np.load(folder / f"{name}.{k}.npy", allow_pickle=False) for k in order[name]}
                 for name in ("pulses", "hits"))


def _resampled(survey: dict, quality: int | None) -> dict:
    """``survey`` with its beam sampled by ``quality`` sub-ray rings (``None``: as it is)."""
    if quality is None:
        return survey
    return dict(survey, overrides=dict(survey.get("overrides") or {}, beam_sample_quality=int(quality)))


def _own_realisation(survey: dict, seed: int) -> dict:
    """``survey`` with a seed of the diagnosis' own (from its ``seed`` and the survey's).

    A survey's seed fixes its trajectory-noise realisation (:mod:`vlsforest.sim.survey`: six
    smooth channels drawn from it, functions of GPS time). A recording made with the same survey
    and seed — the real flight's survey re-planned, or a "real" recording of the virtual forest
    made with the study's seed — would share that realisation with the diagnosis' simulations,
    which would then match its strip offsets sample by sample and fit only an amplitude. A real
    flight's errors are one unknown draw of the process; the diagnosis models the process with a
    draw of its own.
    """
    return dict(survey, seed=lib.derived_seed([seed, survey.get("seed", 0)], 0xD1A9))


class _PlotSim:
    """One plot: its scene, survey, trees and real observables; simulations with caching."""

    def __init__(self, p: PlotInput, seed: int, workers: int, log, beam_sample_quality: int | None = None,
                 spill_dir: Path | None = None):
        from vlsforest.io.las import read_las
        from vlsforest.sim import Scene
        from vlsforest.sim.survey import load_survey_dict

        self.p, self.seed, self.workers, self.log = p, seed, workers, log
        self._spill_dir = spill_dir
        self._keep: set = set()       # keys of traces written to disk when evicted (a later stage reuses them)
        self._spilled: dict = {}      # key → folder of a trace on disk
        self._n_written = 0           # traces written so far (names their folders)
        seg = Path(p.segment)
        if not (seg / "trees.csv").is_file():
            raise InputDataError(f"{seg}: no trees.csv (a 'vlsforest segment' output folder is needed)")
        stems = pd.read_csv(seg / "trees.csv")
        pts = {}
        for tid in stems.tree_id.astype(int):
            f = seg / "trees" / f"{tid}.laz"
            if f.is_file():
                pts[tid] = read_las(f).xyz
        if len(pts) < 5:
            raise InputDataError(f"{seg}: {len(pts)} segmented trees with points; the diagnosis needs ≥ 5 per plot")
        self.tree_points = pts
        self._label = tree_labeller(pts, p.radius, workers)  # every simulation is labelled against these trees
        self.trees = tree_table(pts, stems)
        self.region = _observed_region(pts, self.trees, p.radius, p.margin)
        self.survey = _own_realisation(_resampled(load_survey_dict(p.survey), beam_sample_quality), seed)
        self.survey_dir = Path(p.survey).resolve().parent
        self.has_scaled = False

        def _note_scaled(model):
            self.has_scaled |= model.half is not None
            return model
        self.scene = Scene.from_yaml(p.scene, voxel_transform=_note_scaled)
        real = read_las(p.real)
        self.real = self._features(cloud_arrays(real))
        self._parts = self.scene.part_table()
        self._traces: dict = {}
        self._sims: dict = {}
        self._pinned = None
        self.n_traced = 0
        self.n_loaded = 0
        self.n_redetected = 0

    def _features(self, arrays):
        from vlsforest.extract import ColumnIndex

        columns = ColumnIndex(arrays["xyz"][:, :2])  # for the labels and the features
        lab = self._label(arrays, columns)
        f = tree_features(arrays, lab, self.trees, columns)
        f.index = pd.MultiIndex.from_product([[self.p.name], f.index], names=["plot", "tree_id"])
        return f

    def _survey_for(self, assign):
        """The survey mapping and the scene edits (merged) of a parameter assignment."""
        return lib.apply_all(dict(self.survey), assign)

    def _scene_for(self, edits):
        """The plot's scene, or its voxel reconstruction corrected for TLS occlusion."""
        from vlsforest.sim import Scene

        gain = edits.get("top_gain", 0.0)
        if gain == 0.0:
            return self.scene
        # (scenes without PAD-scaled crowns never get here: diagnose() leaves the candidate out)
        return Scene.from_yaml(self.p.scene, voxel_transform=lambda m: lib.occlusion_corrected(m, gain)
                               if m.half is not None else m)

    def _key(self, assign: dict):
        """What a simulation with ``assign`` runs, as a key: the scanner settings (as the survey
        resolves them), the rest of the survey mapping and the scene edits. Assignments with
        equal keys give the same points (e.g. a divergence scale of 1.0 and the survey as given).

        Returns the key, the survey and the scene edits.
        """
        from vlsforest.sim import survey_from_dict

        s, edits = self._survey_for(assign)
        sv = survey_from_dict(s, base_dir=self.survey_dir)
        rest = {k: v for k, v in s.items() if k != "overrides"}
        return json.dumps([repr(sv.scanner), rest, edits], sort_keys=True, default=str), sv, edits

    def _trace(self, trace_part: dict):
        """The pulses with hits and their hits for the trace-side parameters ``trace_part``.

        Keeps two traces in memory: the search's current baseline (:meth:`pin`) and the last
        other one. A trace of a default-forest plot holds ≈ 120 M sub-ray hits (≈ 3.5 GB); the
        search renders every stored-hit candidate on its baseline's trace and visits trace-side
        values one after the other (their features are cached separately). A trace marked by
        :meth:`keep` is written to the spill folder when it leaves memory and read back when
        asked for again (the next stage's signatures), instead of being traced again.
        """
        from vlsforest.sim import trace_hits

        key, sv, edits = self._key(trace_part)
        if key not in self._traces:
            for k in [k for k in self._traces if k != self._pinned]:
                self._evict(k)
            t0 = time.perf_counter()
            if key in self._spilled:
                self._traces[key] = _load_trace(self._spilled[key])
                self.n_loaded += 1
                self.log(f"  {self.p.name}: read {json.dumps(trace_part)} back from disk in "
                         f"{time.perf_counter() - t0:.1f} s (no new trace)")
                return self._traces[key]
            self._traces[key] = trace_hits(self._scene_for(edits), sv, seed=self.seed, workers=self.workers,
                                           region=self.region)
            _release_freed_memory()
            self.n_traced += 1
            self.log(f"  {self.p.name}: traced {json.dumps(trace_part)} in {time.perf_counter() - t0:.1f} s "
                     f"({len(self._traces[key][1]['pulse']):,} sub-ray hits)")
        return self._traces[key]

    def _evict(self, key) -> None:
        """Drop a trace from memory; first write it to the spill folder if it is kept."""
        trace = self._traces.pop(key)
        if key in self._keep and key not in self._spilled and self._spill_dir is not None:
            self._n_written += 1
            folder = self._spill_dir / f"{self.p.name}-{self._n_written}"
            try:
                _save_trace(folder, trace)
            except OSError as exc:  # e.g. a full disk: the trace is made again when needed
                shutil.rmtree(folder, ignore_errors=True)
                self._keep.discard(key)
                self.log(f"  {self.p.name}: could not keep a trace on disk ({exc}); it is traced again if needed")
            else:
                self._spilled[key] = folder

    def keep(self, assigns: list, spill: bool = True) -> None:
        """The traces of ``assigns`` are this stage's: traces on disk that are not are deleted,
        and (with ``spill``) these are written to disk when they leave memory."""
        needed = {self.trace_key(a) for a in assigns}
        for k in [k for k in self._spilled if k not in needed]:
            shutil.rmtree(self._spilled.pop(k))
        self._keep = needed if spill else set()

    def trace_key(self, assign: dict) -> str:
        """The key of the trace that ``assign`` renders from (its trace-side part's :meth:`_key`)."""
        return self._key(_trace_part(assign))[0]

    def pin(self, assign: dict) -> None:
        """Keep the trace of ``assign`` (the search's baseline) cached until the next pin."""
        self._pinned = self.trace_key(assign)

    def features(self, assign: dict) -> pd.DataFrame:
        from vlsforest.sim import redetect

        key, sv, edits = self._key(assign)
        if key not in self._sims:
            pulses, hits = self._trace(_trace_part(assign))
            parts = dict(self._parts,
                         reflectance=np.clip(self._parts["reflectance"] * edits["reflectance_scale"], 0, 1))
            if "specularity" in edits:
                parts["specularity"] = np.full(len(parts["specularity"]), edits["specularity"])
                parts["shininess"] = np.full(len(parts["shininess"]), lib.SHININESS)
            res = redetect(parts, pulses, hits, sv, seed=self.seed)
            self.n_redetected += 1
            self._sims[key] = self._features(cloud_arrays(res))
        return self._sims[key]


class _Study:
    """All plots together: observables of real and simulated trees, cached per parameter set."""

    def __init__(self, setup: Setup, log, spill_dir: Path | None = None):
        self.plots = [_PlotSim(p, setup.seed, setup.workers, log, setup.beam_sample_quality, spill_dir)
                      for p in setup.plots]
        self.real = pd.concat([p.real for p in self.plots])
        self._cache: dict = {}

    def pin(self, assign: dict) -> None:
        """Keep the traces of ``assign`` (the search's current baseline) cached in every plot."""
        for p in self.plots:
            p.pin(assign)

    def keep(self, assigns: list, spill: bool = True) -> None:
        """The traces of this stage's signatures: written to disk once they leave memory (with
        ``spill``: a later stage may read them back); other traces on disk are deleted."""
        for p in self.plots:
            p.keep(assigns, spill)

    def sim(self, assign: dict) -> pd.DataFrame:
        key = json.dumps(assign, sort_keys=True)
        if key not in self._cache:
            self._cache[key] = pd.concat([p.features(assign) for p in self.plots])
        return self._cache[key]

    def has_trace(self, assign: dict) -> bool:
        """Whether every plot holds the ray trace that ``assign`` renders from (no new trace)."""
        return all(p.trace_key(assign) in p._traces for p in self.plots)

    def residual(self, assign: dict) -> np.ndarray:
        s = self.sim(assign).reindex(self.real.index)
        return (self.real - s).to_numpy(float)

    @property
    def n_traced(self):
        return sum(p.n_traced for p in self.plots)

    @property
    def n_loaded(self):
        return sum(p.n_loaded for p in self.plots)

    @property
    def has_scaled(self):
        """Whether every plot's scene has PAD-scaled voxel crowns (``tls_occlusion`` applies)."""
        return all(p.has_scaled for p in self.plots)

    @property
    def survey(self):
        return self.plots[0].survey


_merge = lib.merge


def _grid(par: lib.Param, lo: float, hi: float, base: float, n: int) -> np.ndarray:
    if par.integer:
        g = np.arange(int(np.ceil(lo)), int(np.floor(hi)) + 1, dtype=float)
        if len(g) > n:
            g = np.unique(np.round(np.linspace(lo, hi, n)))
        return g
    if par.log and lo > 0:
        g = np.geomspace(lo, hi, n)
    elif par.log and lo == 0:  # a wide prior from 0: zero, then log-spaced
        g = np.r_[0.0, np.geomspace(hi / 1000.0, hi, n - 1)]
    else:
        g = np.linspace(lo, hi, n)
    return np.unique(np.r_[g, base])


# ------------------------------------------------------------------------------------ the steps
def _attribute(study: _Study, base: dict, cands: list, D0: np.ndarray, w: np.ndarray, last: bool = True):
    """Signatures, projections, scores and groups of every candidate (relative to ``base``).

    Unless this is the ``last`` stage, the candidates' traces go to disk when they leave memory:
    when the stage accepts a stored-hit effect (threshold, window, noise, …), the next stage's
    signatures render the same traces again with the new baseline, and read them back instead of
    tracing them.
    """
    rbar = np.nanmean(D0, axis=0)
    project = st.project
    S0 = study.sim(base).reindex(study.real.index).to_numpy(float)
    steps = {c.name: c.step(c.current(study.survey, base), study.survey) for c in cands}
    study.keep([_merge(base, c.name, steps[c.name]) for c in cands], spill=not last)
    # simulate the candidates whose trace is still held first: a trace-side candidate traced last
    # in the previous round is not traced again after the others evicted it (same results)
    for c in sorted(cands, key=lambda c: not study.has_trace(_merge(base, c.name, steps[c.name]))):
        study.sim(_merge(base, c.name, steps[c.name]))
    rows, sigs = [], {}
    for c in cands:
        cur = c.coords(c.current(study.survey, base))
        p0 = c.params[0]
        lo = c.bounds(study.survey)[p0.name][0]
        pert = steps[c.name]
        S1 = study.sim(_merge(base, c.name, pert)).reindex(study.real.index).to_numpy(float)
        J = np.nanmean(S1 - S0, axis=0)  # common random numbers: same pulses and seed
        sigs[c.name] = J
        a, ev, cos = project(rbar, J, w)
        step = c.coords(pert)[p0.name] - cur[p0.name]
        implied = cur[p0.name] + a * step
        possible = bool(implied >= lo - 1e-9)  # below the lower bound: a physically impossible sign
        score = (ev if possible else 0.0) - PENALTY * len(c.params)
        t, p = st.amplitude_test(D0, J, w)
        rows.append({"name": c.name, "group": c.group, "amplitude": a, "explained_fraction": max(ev, 0.0),
                     "t": t, "p_matched": min(1.0, p * len(cands)),
                     "possible_sign": bool(possible), "implied": implied, "score": score,
                     "mde": st.mde(J, D0) * abs(step), "step": step})
    # significant (matched filter, Bonferroni over candidates) and physically possible first
    ranked = sorted(rows, key=lambda r: (not (r["p_matched"] < ALPHA and r["possible_sign"]), -r["score"]))
    names = [r["name"] for r in ranked]
    cosm = {(a, b): st.cosine(sigs[a], sigs[b], w) for a in names for b in names}
    return ranked, sigs, cosm


def _tie_break(ranked, sigs, cosm, D0, w):
    """Resolve a tie between the leader and look-alikes on the group's separating observables."""
    lead = ranked[0]
    rivals = [r for r in ranked[1:] if (r["group"] == lead["group"] or abs(cosm[(lead["name"], r["name"])]) > 0.9)
              and lead["score"] - r["score"] < TIE_MARGIN and r["score"] > 0]
    if not rivals:
        return ranked, None
    # the separating observables of every group in the tie: a look-alike from another group is
    # told apart by its own group's observables as much as by the leader's
    groups = list(dict.fromkeys([lead["group"]] + [r["group"] for r in rivals]))
    tb = tuple(dict.fromkeys(f for g in groups for f in lib.TIE_BREAKERS.get(g, ())))
    idx = [FEATURES.index(f) for f in tb]
    mask = np.zeros(len(FEATURES))
    mask[idx] = 1.0
    rbar = np.nanmean(D0, axis=0)
    scored = []
    for r in [lead] + rivals:
        _, ev, _ = st.project(rbar, sigs[r["name"]], w * mask)
        scored.append((ev, r["name"]))
    scored.sort(key=lambda x: -x[0])
    resolved = len(scored) < 2 or scored[0][0] - scored[1][0] >= TIE_RESOLVE
    if resolved:
        winner = scored[0][1]
    else:  # the separating observables do not separate: the simplest member speaks for the group
        winner = min((n for _, n in scored), key=lambda n: (len(lib.CANDIDATES[n].value_keys), n != lead["name"]))
    where = (f"{lead['group']} group" if len(groups) == 1 else
             "tie of look-alikes from the " + " and ".join(groups) + " groups")
    note = {"group": lead["group"], "groups": groups, "members": [n for _, n in scored], "tie_breakers": list(tb),
            "explained_on_tie_breakers": {n: round(float(e), 3) for e, n in scored}, "winner": winner,
            "resolved": bool(resolved),
            "text": (f"{winner} wins the {where} on {', '.join(tb)}" if resolved else
                     f"the {where} ({', '.join(n for _, n in scored)}) is not separated by "
                     f"{', '.join(tb)}; the simplest member, {winner}, is fitted for the group")}
    if winner != lead["name"]:
        ranked = [r for r in ranked if r["name"] == winner] + [r for r in ranked if r["name"] != winner]
    return ranked, note


def _fit(study: _Study, base: dict, cand: lib.Candidate, w: np.ndarray, folds: np.ndarray, n_grid: int,
         rng: np.random.Generator):
    """Grid fit of a candidate (coordinate search over its searched parameters, from the values
    ``base`` simulates).

    Returns the all-tree and per-fold values (as :meth:`Candidate.apply` takes them) and a
    mapping with ``votes`` (per searched
    parameter: observable → its crossing and its share of the weight; empty where the
    least-squares grid minimum was taken), ``rests_on`` (for a parameter whose fit rests on one
    observable, more than :data:`DOMINANT_VOTE` of the weight: that observable, its share and
    the value fitted without it), ``between_observables`` (per parameter: the crossings'
    ``scale_factor`` S — their disagreement beyond sampling, ≈ 1 when they agree — and the
    estimate's ``systematic_sd`` beyond sampling, on the log scale where ``log_scale``; the
    bias allowance's entries are added by :func:`_systematic_ci`), ``ci95_trees`` (the first
    searched parameter's 95 % CI from the bootstrap over trees; :func:`_systematic_ci` widens
    it), ``curve`` (the first parameter's grid and residuals, for :func:`_realisation_scatter`)
    and ``voters`` (the first parameter's voters' weight shares and bias shifts and every
    parameter's voters, for :func:`_systematic_ci`); the last two are not for the report."""
    start = cand.current(study.survey, base)
    cur = cand.coords(start)
    bounds = cand.bounds(study.survey)
    k = int(folds.max()) + 1
    per_fold = [dict(cur) for _ in range(k)]
    allv = dict(cur)
    curves, votes, rests_on, spread, used = {}, {}, {}, {}, set()
    for par in cand.params:
        lo, hi = bounds[par.name]
        if par.n_grid:  # its own grid, through the reference step (simulated for the signature)
            g = np.unique(np.r_[_grid(par, lo, hi, cur[par.name], par.n_grid),
                                cand.step_coords(start, study.survey)[par.name]])
        else:
            g = _grid(par, lo, hi, cur[par.name], n_grid if par is cand.params[0] else max(n_grid - 2, 3))
        Ds = []
        for v in g:
            val = dict(allv)
            val[par.name] = float(v)
            Ds.append(study.residual(_merge(base, cand.name, cand.values(start, val))))
        curves[par.name] = (g, Ds)
        lg = par.log and lo > 0
        allv[par.name], v, spread[par.name] = st.crossing_votes(g, Ds, w, lo, hi, lg, detail=True)
        total = sum(q for _, q in v.values())
        used |= set(v)
        if par is cand.params[0]:  # its voters' weight shares and bias shifts, for the bias allowance
            voters = {"shares": {j: q / total for j, (_, q) in v.items()} if total > 0 else {},
                      "bias_shift": spread[par.name].get("bias_shift", {})}
        votes[par.name] = {FEATURES[j]: {"crossing": r, "weight_share": q / total if total > 0 else 0.0}
                           for j, (r, q) in sorted(v.items(), key=lambda kv: -kv[1][1])}
        top = max(v, key=lambda j: v[j][1]) if total > 0 else None
        if top is not None and v[top][1] > DOMINANT_VOTE * total:  # the fit rests on one observable
            w_out = w.copy()
            w_out[top] = 0.0
            rests_on[par.name] = {"observable": FEATURES[top], "weight_share": v[top][1] / total,
                                  "without_it": st.robust_fit(g, Ds, w_out, lo, hi, lg)}
        for f in range(k):
            per_fold[f][par.name] = st.robust_fit(g, Ds, w, lo, hi, lg, rows=folds != f)
        if par.integer:
            allv[par.name] = float(round(allv[par.name]))
            for f in range(k):
                per_fold[f][par.name] = float(round(per_fold[f][par.name]))
    # bootstrap CI over trees of the (first) parameter from the grid curve
    par = cand.params[0]
    g, Ds = curves[par.name]
    lo, hi = bounds[par.name]
    n = len(folds)
    boot = []
    for _ in range(300):
        rows = rng.integers(0, n, n)
        boot.append(st.robust_fit(g, Ds, w, lo, hi, par.log and lo > 0, rows=rows))
    ci_trees = [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))]
    between = {q.name: {"scale_factor": spread[q.name]["scale_factor"],
                        "systematic_sd": spread[q.name]["systematic_sd"],
                        "log_scale": bool(q.log and bounds[q.name][0] > 0)}
               for q in cand.params if spread.get(q.name)}
    return (cand.values(start, allv), [cand.values(start, v) for v in per_fold],
            {"votes": votes, "rests_on": rests_on, "between_observables": between,
             "ci95_trees": {par.name: ci_trees}, "curve": curves[par.name], "voters": dict(voters, used=used)})


def _systematic_ci(cand: lib.Candidate, survey: dict, allv: dict, fit_info: dict, voters: dict,
                   D_left: np.ndarray, w: np.ndarray) -> list:
    """The first searched parameter's 95 % CI: the bootstrap over trees (``ci95_trees``) widened,
    in quadrature, by the SD the voters' systematic errors give the estimate — the larger of two
    estimates of it. One is the votes' disagreement beyond sampling (``systematic_sd``,
    :func:`.stats.crossing_votes`), which sees such errors only where several voters of
    comparable precision disagree. The other is the bias allowance
    (:func:`.stats.bias_allowance`): the voters are taken to carry biases as large, in
    across-tree SDs, as those the fit leaves in the observables it did not use (``D_left``, the
    held-out residuals; β from :func:`.stats.bias_scale`), which also covers a fit that rests on
    one observable. Records ``bias_scale``, ``bias_sd`` and ``n_unused`` in
    ``fit_info["between_observables"]``."""
    par = cand.params[0]
    lo, hi = cand.bounds(survey)[par.name]
    log = bool(par.log and lo > 0)
    rest = [k for k in range(len(FEATURES)) if w[k] > 0 and k not in voters["used"]]
    beta = st.bias_scale(D_left, rest)
    sd = st.bias_allowance(beta, voters["shares"], voters["bias_shift"])
    row = fit_info["between_observables"].setdefault(par.name, {"scale_factor": None, "systematic_sd": 0.0,
                                                                 "log_scale": log})
    row.update(bias_scale=beta, bias_sd=sd, n_unused=len(rest))
    return _widened(fit_info["ci95_trees"][par.name], cand.coords(allv)[par.name], max(sd, row["systematic_sd"]),
                    log, lo, hi)


def _widened(ci: list, x: float, sd: float, log: bool, lo: float, hi: float) -> list:
    """``ci`` about ``x`` with ``± 1.96 sd`` added in quadrature on each side (on the log scale
    for ``log``), within the bounds."""
    if not sd > 0:
        return list(ci)
    to, back = (np.log, np.exp) if log and x > 0 and ci[0] > 0 else (float, float)
    t, a, b = to(x), to(ci[0]), to(ci[1])
    return [float(max(lo, back(t - np.hypot(max(t - a, 0.0), 1.96 * sd)))),
            float(min(hi, back(t + np.hypot(max(b - t, 0.0), 1.96 * sd))))]


def _realisation_scatter(study: _Study, base: dict, cand: lib.Candidate, allv: dict, curve: tuple,
                         w: np.ndarray, n: int) -> dict:
    """The scatter of a random candidate's fit between draws of its process, and the fit
    averaged over the draws.

    Draws 1 … ``n`` of the process are simulated at the fitted value ``x`` (``allv``); each is
    taken as if it were the recording and fitted on the all-tree grid ``curve`` (draw 0's
    simulations) the way the diagnosis fits (:func:`.stats.robust_fit`, weights ``w``). Draw r
    fits at ``x · a_r / a_0``, ``a`` being the draws' amplitudes (how strongly each moves the
    observables), so ``c = (1, x_1 / x, …, x_n / x)`` are ``n + 1`` draws' amplitudes up to one
    factor, and their relative SD (``ddof = 1``) is that of one draw (``relative_sd_one_draw``).
    Using draw 0 as one of the samples keeps this from depending on whether draw 0 happened to be
    a weak or a strong one.

    Draw 0's fit ``x`` matches the recording's draw with the simulation's draw 0: it is
    ``σ · a_real / a_0`` and carries both draws' scatter. Matched with the mean amplitude of
    the ``n + 1`` simulated draws instead, the estimate is ``x / mean(c)`` (``fitted_mean``):
    the simulation's part of the scatter shrinks by ``√(n + 1)``, the recording's own draw stays,
    so its relative SD is ``relative_sd_one_draw · √(1 + 1 / (n + 1))`` (``relative_sd``; the
    fit of draw 0 alone had ``√2`` times that of one draw). ``draw0_fit`` keeps ``x``, the value
    draw 0 needs to reproduce the recording, which the diagnosis goes on simulating.
    """
    par = cand.params[0]
    g, Ds = curve
    lo, hi = cand.bounds(study.survey)[par.name]
    x = cand.coords(allv)[par.name]
    vals = []
    for r in range(1, n + 1):
        Dr = study.residual(_merge(base, cand.name, dict(allv, realisation=r)))
        # draw r's simulation as the recording: (real − sim_0(g)) − (real − sim_r(x)) = sim_r(x) − sim_0(g)
        vals.append(st.robust_fit(g, [D - Dr for D in Ds], w, lo, hi, par.log and lo > 0))
    c = np.r_[1.0, np.asarray(vals) / x] if x > 0 else np.array([np.nan])
    ok = len(c) > 1 and np.isfinite(c).all() and np.mean(c) > 0
    one = float(np.std(c, ddof=1) / np.mean(c)) if ok else float("nan")
    mean_x = float(np.clip(x / np.mean(c), lo, hi)) if ok else float(x)
    return {"n": n, "fitted": [float(v) for v in vals], "draw0_fit": float(x),
            "mean_amplitude": float(np.mean(c)) if ok else float("nan"), "fitted_mean": mean_x,
            "relative_sd_one_draw": one, "relative_sd": float(one * np.sqrt(1.0 + 1.0 / len(c)))}


def diagnose(setup: Setup, log=None, work_dir=None) -> dict:
    """Run the diagnosis (see the module docstring); return the report mapping.

    Parameters
    ----------
    setup : Setup
    log : callable, optional
        Takes each progress line (default: print to stderr).
    work_dir : path, optional
        Where a temporary folder may hold ray traces that a later stage reads back instead of
        tracing again (up to one per trace-side candidate, ≈ 3.5 GB each on the default forest);
        it is deleted before returning. Without it every trace is made anew when needed.
    """
    spill = None
    if work_dir is not None:
        try:
            Path(work_dir).mkdir(parents=True, exist_ok=True)
            spill = Path(tempfile.mkdtemp(prefix=".diagnose-traces-", dir=work_dir))
        except OSError as exc:
            raise ConfigError(f"{work_dir}: cannot hold the diagnosis' temporary traces there "
                              f"({exc.strerror or exc})") from None
    try:
        return _diagnose(setup, log or (lambda m: print(f"diagnose: {m}", file=sys.stderr, flush=True)), spill)
    finally:
        if spill is not None:
            shutil.rmtree(spill, ignore_errors=True)


def _diagnose(setup: Setup, log, spill_dir) -> dict:
    t0 = time.perf_counter()
    rng = np.random.default_rng(setup.seed)
    study = _Study(setup, log, spill_dir)
    cands = lib.select(setup.candidates)
    if not study.has_scaled and any(c.name == "tls_occlusion" for c in cands):
        if setup.candidates_given:
            raise ConfigError("candidate tls_occlusion corrects PAD-scaled voxel crowns, but a plot's scene has "
                              "none (a fixed-size method?); leave it out of 'candidates'")
        cands = [c for c in cands if c.name != "tls_occlusion"]
        log("tls_occlusion left out: the scenes have no PAD-scaled voxel crowns")
    base: dict = {}
    study.pin(base)
    D0 = study.residual(base)
    have = np.isfinite(study.real.to_numpy(float)).any(axis=1)
    n_trees = int(have.sum())
    if n_trees < 10:
        raise InputDataError(f"only {n_trees} trees with enough real points; the diagnosis needs ≥ 10")
    w = st.weights(D0)
    loc = st.locate(D0, seed=setup.seed)
    mism = []
    for j, f in enumerate(FEATURES):
        if np.isfinite(loc["q"][j]) and loc["q"][j] < ALPHA:
            mism.append({"metric": f, "stratum": STRATUM[f], "mean_residual": float(loc["mean"][j]),
                         "ci95": [float(loc["ci_lo"][j]), float(loc["ci_hi"][j])], "q": float(loc["q"][j]),
                         "n_trees": int(loc["n"][j]),
                         "text": f"{f} ({STRATUM[f]}): real − simulated = {loc['mean'][j]:+.3g} "
                                 f"[{loc['ci_lo'][j]:+.3g}, {loc['ci_hi'][j]:+.3g}], q = {loc['q'][j]:.2g}"})
    mism.sort(key=lambda m: m["q"])
    significant = bool(loc["global_p"] < ALPHA or mism)
    log(f"{n_trees} trees; global p = {loc['global_p']:.3g}; {len(mism)} observables differ (BH q < {ALPHA})")
    # folds across trees (fixed by the seed)
    order = rng.permutation(len(D0))
    folds = np.empty(len(D0), int)
    folds[order] = np.arange(len(D0)) % setup.folds

    effects, accepted, rounds = [], [], []
    group_note = {}  # accepted effect → what it stands for when its group's members were not separated
    current_D = D0
    final_D = D0  # the held-out residuals after the last accepted effect
    remaining = list(cands)
    for stage in range(MAX_EFFECTS if significant else 0):
        last = stage + 1 >= MAX_EFFECTS or len(remaining) < 2
        ranked, sigs, cosm = _attribute(study, base, remaining, current_D, w, last=last)
        ranked, tie = _tie_break(ranked, sigs, cosm, current_D, w)
        rounds.append({"stage": stage + 1, "ranking": [{k: (round(v, 4) if isinstance(v, float) else v)
                                                         for k, v in r.items()} for r in ranked],
                       "tie": tie})
        lead = ranked[0]
        log(f"stage {stage + 1}: " + ", ".join(f"{r['name']} {r['explained_fraction']:.2f}" for r in ranked[:4]))
        ev_crit = st.chance_ev(int(np.sum(np.isfinite(np.nanmean(current_D, axis=0)) & (w > 0))), len(remaining))
        rounds[-1]["chance_explained_fraction"] = ev_crit
        if (lead["explained_fraction"] < max(MIN_EV, ev_crit) or not lead["possible_sign"]
                or lead["p_matched"] >= ALPHA):
            break
        cand = lib.CANDIDATES[lead["name"]]
        # fit on the observables the candidate informs: weights scaled by the squared
        # signal-to-noise of its signature (reconstruction errors elsewhere do not pull the fit)
        wfit = w * st.information_weights(sigs[cand.name], current_D)
        allv, per_fold, fit_info = _fit(study, base, cand, wfit, folds, setup.grid, rng)
        curve, voters = fit_info.pop("curve"), fit_info.pop("voters")
        # held-out: each fold simulated at the value fitted without it
        D_after = np.full_like(current_D, np.nan)
        for f, val in enumerate(per_fold):
            Df = study.residual(_merge(base, cand.name, val))
            D_after[folds == f] = Df[folds == f]
        ci = _systematic_ci(cand, study.survey, allv, fit_info, voters, D_after, w)
        before = st.tree_loss(current_D, w)
        after = st.tree_loss(D_after, w)
        p = st.paired_improvement(before, after)
        worse = st.worse_metrics(current_D, D_after, FEATURES)
        eb, ea = float(np.nanmean(before)), float(np.nanmean(after))
        # accepted on the held-out total error; observables that got significantly worse are
        # reported (the voxel model's own error there was compensating the missing physics)
        ok = p < ALPHA and ea < eb
        at_bound = any(np.isclose(cand.coords(allv)[q.name], b, rtol=1e-3) for q in cand.params
                       for b in cand.bounds(study.survey)[q.name])
        change = {f: {"before": _nanmean(current_D[:, j]), "after": _nanmean(D_after[:, j])}
                  for j, f in enumerate(FEATURES)}
        effects.append({"name": cand.name, "group": cand.group, "parameters": {k: float(v) for k, v in allv.items()},
                        "ci95": {cand.params[0].name: ci}, "baseline": cand.current(study.survey, base),
                        "explained_fraction": float(lead["explained_fraction"]),
                        "heldout_error_before": eb, "heldout_error_after": ea, "p_value": p,
                        "worse_metrics": worse, "heldout_mean_residual": change,
                        "at_prior_bound": bool(at_bound), "accepted": bool(ok),
                        "per_fold": per_fold, **fit_info, "stage": stage + 1})
        if cand.group == "footprint":  # what every member of the group would fit: the solid angle
            eq = lib.equivalent_circular_divergence(study.survey, _merge(base, cand.name, allv))
            effects[-1]["equivalent_circular_fwhm_mrad"] = eq
            if tie is not None and not tie["resolved"] and tie["winner"] == cand.name:
                tie["text"] += (f"; it fits a beam of the solid angle of a {eq:.3g} mrad (FWHM) circle, i.e. any "
                                f"beam with major × minor = {eq * eq:.3g} mrad² (the members' aspect ratios are "
                                f"not identified)")
                group_note[cand.name] = (f" (for the footprint group: a beam of major × minor = {eq * eq:.3g} mrad² "
                                         f"at FWHM; ellipse and circle not separated)")
        log(f"  fitted {cand.name} = {allv} (CI {ci}); held-out error {eb:.3f} → {ea:.3f}, p = {p:.3g}"
            f"{'; worse: ' + ', '.join(worse) if worse else ''} → {'accepted' if ok else 'rejected'}")
        if ok and cand.realisations and setup.realisations > 0:
            sc = _realisation_scatter(study, base, cand, allv, curve, wfit, setup.realisations)
            pn = cand.params[0].name
            blo, bhi = cand.bounds(study.survey)[pn]
            if np.isfinite(sc["relative_sd"]):
                # the estimate matched with the draws' mean amplitude; the CI so far (draw 0's, of
                # which every fit scales alike) moved with it and widened by the scatter that
                # remains (the recording's draw and the mean of the simulated ones), in quadrature
                x, k = sc["fitted_mean"], sc["fitted_mean"] / sc["draw0_fit"]
                effects[-1]["parameters"] = {kk: float(v) for kk, v in
                                             cand.values(cand.current(study.survey, base), {pn: x}).items()}
                moved = [float(np.clip(v * k, blo, bhi)) for v in ci]
                effects[-1]["ci95"] = {pn: _widened(moved, x, sc["relative_sd"] * x, False, blo, bhi)}
            effects[-1]["realisation_scatter"] = sc
            log(f"  {sc['n']} further draws of its process fit {', '.join(f'{v:.3g}' for v in sc['fitted'])}; "
                f"matched with the draws' mean {pn} = {sc['fitted_mean']:.3g} (draw 0 alone: {sc['draw0_fit']:.3g}, "
                f"relative SD {sc['relative_sd']:.2f}); CI {effects[-1]['ci95'][pn]}")
        if not ok:
            break
        accepted.append(cand.name)
        final_D = D_after
        base = _merge(base, cand.name, allv)
        remaining = [c for c in remaining if c.name != cand.name]
        if last:  # no further stage needs the residuals of the all-tree fit (no simulation of it)
            break
        study.pin(base)
        current_D = study.residual(base)
    for r in (rounds[0]["ranking"] if rounds else []):
        if r["name"] not in {e["name"] for e in effects}:
            effects.append({"name": r["name"], "group": r["group"], "parameters": {},
                            "explained_fraction": r["explained_fraction"], "heldout_error_before": None,
                            "heldout_error_after": None, "p_value": None, "accepted": False,
                            "stage": None})
    beam = lib.beam_fwhm(study.survey, base)  # the beam the accepted effects simulate
    if "elliptical_footprint" in accepted:  # its aspect identified: the group stands for this beam
        group_note.pop("beam_divergence", None)
        group_note["elliptical_footprint"] = f" (the beam: {beam[0]:.3g} × {beam[1]:.3g} mrad at FWHM)"
    for e in effects:  # a fit that rests on one observable says so, with the value without it
        if e.get("accepted") and e.get("rests_on"):
            group_note[e["name"]] = group_note.get(e["name"], "") + "".join(
                f" ({par}: {r['observable']} carries {100 * r['weight_share']:.0f} % of the fit's weight; "
                f"{r['without_it']:.3g} without it)" for par, r in e["rests_on"].items())
    if not significant:
        verdict = "no significant mismatch"
    elif accepted:
        def fitted(e):  # the first searched parameter's value and CI
            c = lib.CANDIDATES[e["name"]]
            par = c.params[0].name
            x, (lo, hi) = c.coords(e["parameters"])[par], e["ci95"][par]
            return f" [{par} = {x:.3g}, 95 % CI {lo:.3g}–{hi:.3g}]"

        eff_of = {e["name"]: e for e in effects if e.get("accepted")}
        verdict = "mismatch explained by " + " + ".join(a + fitted(eff_of[a]) + group_note.get(a, "") for a in accepted)
        worse = sorted({m for e in effects if e.get("accepted") for m in e.get("worse_metrics", [])})
        if worse:
            verdict += f" (held-out {', '.join(worse)} got worse: the voxel model's own error compensated there)"
    else:
        verdict = "mismatch found, not attributable"
    mde = {r["name"]: r["mde"] for r in rounds[0]["ranking"]} if rounds else {}
    # the diagnosis' cost; the oracle's simulations (benchmarks only) are counted apart
    cost = {"traced_simulations": study.n_traced, "traces_read_back": study.n_loaded,
            "seconds": round(time.perf_counter() - t0, 1)}
    oracle = None
    if setup.oracle is not None:
        D_or = study.residual({k: dict(v) for k, v in setup.oracle.items()})
        D_fit = study.residual(base)
        oracle = {"values": setup.oracle, "error_given": float(np.nanmean(st.tree_loss(D0, w))),
                  "error_told_truth": float(np.nanmean(st.tree_loss(D_or, w))),
                  "error_fitted": float(np.nanmean(st.tree_loss(D_fit, w))),
                  # observables significantly worse when told the truth (the voxel model's own
                  # error compensated there), and worse with the fitted values than with the truth
                  "worse_told_truth": st.worse_metrics(D0, D_or, FEATURES),
                  "worse_fitted_than_truth": st.worse_metrics(D_or, D_fit, FEATURES),
                  # what is left when told the truth (the reconstruction's own error, per observable)
                  "residual_told_truth": {f: (float(np.nanmean(D_or[:, j])) if np.isfinite(D_or[:, j]).any()
                                              else None) for j, f in enumerate(FEATURES)},
                  "cost": {"traced_simulations": study.n_traced - cost["traced_simulations"],
                           "seconds": round(time.perf_counter() - t0 - cost["seconds"], 1)}}
    rep = {
        "scenario": setup.scenario,
        "metric": "diagonal",  # explained fractions weigh each observable by 1 / its across-tree variance
        "plots": [p.name for p in setup.plots],
        "n_trees": n_trees,
        "significant_mismatch": significant,
        "global_p": loc["global_p"],
        "mismatches": mism,
        "effects": effects,
        "accepted": accepted,
        "model": base,
        "beam_fwhm_mrad": [float(beam[0]), float(beam[1])],
        "verdict": verdict,
        "rounds": rounds,
        "minimum_detectable_effect": mde,
        "residual_after": {f: (float(np.nanmean(final_D[:, j])) if np.isfinite(final_D[:, j]).any() else None)
                           for j, f in enumerate(FEATURES)},
        "residual_before": {f: (float(loc["mean"][j]) if np.isfinite(loc["mean"][j]) else None)
                            for j, f in enumerate(FEATURES)},
        "residual_sd": {f: _nanstd(D0[:, j]) for j, f in enumerate(FEATURES)},
        "oracle": oracle,
        "cost": cost,
    }
    log(f"verdict: {verdict} ({cost['traced_simulations']} traced simulations, {cost['traces_read_back']} read "
        f"back from disk, {cost['seconds']:.0f} s)")
    return _clean(rep)


def _nanstd(x):
    x = x[np.isfinite(x)]
    return float(x.std(ddof=1)) if len(x) > 1 else None


def _nanmean(x):
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else None


def _clean(o):
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (np.floating, float)):
        return None if not np.isfinite(o) else float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o
