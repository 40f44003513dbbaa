"""The diagnosis' simulations: per tree, the observables of the real recording and of a simulation
with candidate physics applied, cached per parameter assignment.

:class:`PlotSim` holds one plot — its scene, survey, trees and real observables — and simulates
a parameter assignment (candidate id → values) by ray tracing what changes the trace and
re-rendering stored hits for the rest (:class:`~vlsforest.diagnose.traces.TraceCache`);
:class:`Study` joins the plots.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from vlsforest.diagnose import library as lib
from vlsforest.diagnose.features import GROUND_PAD_M, cloud_arrays, tree_features, tree_labeller, tree_table
from vlsforest.diagnose.setup import PlotInput, Setup
from vlsforest.diagnose.traces import TraceCache
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.csvfile import read_csv_table


def trace_part(assign: dict) -> dict:
    """The candidates of ``assign`` that need a new ray trace (the rest re-renders stored hits)."""
    return {k: v for k, v in assign.items() if lib.CANDIDATES[k].render == "trace"}


def resampled(survey: dict, quality: int | None) -> dict:
    """``survey`` with its beam sampled by ``quality`` sub-ray rings (``None``: as it is)."""
    if quality is None:
        return survey
    return dict(survey, overrides=dict(survey.get("overrides") or {}, beam_sample_quality=int(quality)))


def own_realisation(survey: dict, seed: int) -> dict:
    """``survey`` with a seed of the diagnosis' own (from its ``seed`` and the survey's).

    A survey's seed fixes its trajectory-noise realisation (:mod:`vlsforest.sim.trajectory`: six
    smooth channels drawn from it, functions of GPS time). A recording made with the same survey
    and seed — the real flight's survey re-planned, or a "real" recording of the virtual forest
    made with the study's seed — would share that realisation with the diagnosis' simulations,
    which would then match its strip offsets sample by sample and fit only an amplitude. A real
    flight's errors are one unknown draw of the process; the diagnosis models the process with a
    draw of its own.
    """
    return dict(survey, seed=lib.derived_seed([seed, survey.get("seed", 0)], 0xD1A9))


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


def _airborne(survey: dict, where) -> dict:
    """``survey`` if its platform flies lines (the observables read flight lines and scan
    angles); a static (TLS) platform is a configuration error."""
    platform = survey.get("platform") if isinstance(survey, dict) else None
    kind = platform.get("type", "linear") if isinstance(platform, dict) else "linear"
    if kind != "linear":
        raise ConfigError(f"{where}: the diagnosis compares airborne recordings, but this survey's platform is "
                          f"{kind!r} (it needs a linear platform)")
    return survey


class PlotSim:
    """One plot: its scene, survey, trees and real observables; simulations with caching.

    Parameters
    ----------
    p : PlotInput
    seed, workers : int
        The simulations' seed and the ray traces' worker processes.
    log : callable
        Takes each progress line.
    beam_sample_quality : int, optional
        Sub-ray rings of every simulation (None: the survey's).
    spill_dir : Path, optional
        Where traces that a later stage reads back wait (:class:`TraceCache`).
    """

    def __init__(self, p: PlotInput, seed: int, workers: int, log, beam_sample_quality: int | None = None,
                 spill_dir: Path | None = None):
        from vlsforest.io.las import read_las
        from vlsforest.sim import Scene
        from vlsforest.sim.survey import load_survey_dict

        self.p, self.seed, self.workers, self.log = p, seed, workers, log
        self.traces = TraceCache(p.name, log, spill_dir)
        seg = Path(p.segment)
        if not (seg / "trees.csv").is_file():
            raise InputDataError(f"{seg}: no trees.csv (a 'vlsforest segment' output folder is needed)")
        stems = read_csv_table(seg / "trees.csv", "tree table", ids=("tree_id",), numbers=("x", "y", "z"))
        pts = {}
        for tid in stems.tree_id.tolist():
            f = seg / "trees" / f"{tid}.laz"
            if f.is_file():
                pts[tid] = read_las(f).xyz
        if len(pts) < 5:
            raise InputDataError(f"{seg}: {len(pts)} segmented trees with points; the diagnosis needs ≥ 5 per plot")
        self.tree_points = pts
        self._label = tree_labeller(pts, p.radius, workers)  # every simulation is labelled against these trees
        self.trees = tree_table(pts, stems)
        self.region = _observed_region(pts, self.trees, p.radius, p.margin)
        survey = _airborne(load_survey_dict(p.survey), p.survey)
        self.survey = own_realisation(resampled(survey, beam_sample_quality), seed)
        self.survey_dir = Path(p.survey).resolve().parent
        self.has_scaled = False

        def _note_scaled(model):
            self.has_scaled |= model.half is not None
            return model
        self.scene = Scene.from_yaml(p.scene, voxel_transform=_note_scaled)
        real = read_las(p.real)
        self.real = self.observables(cloud_arrays(real))
        #: the scene's parts (reflectance, specularity, shininess per part) the re-detection reads
        self.parts = self.scene.part_table()
        self._sims: dict = {}
        self._offsets = (None, None)  # (trace key, hit_offsets of that trace)
        self.n_redetected = 0

    @property
    def n_traced(self) -> int:
        """Traces made so far."""
        return self.traces.n_traced

    @property
    def n_loaded(self) -> int:
        """Traces read back from disk so far."""
        return self.traces.n_loaded

    def observables(self, arrays: dict) -> pd.DataFrame:
        """Per tree of the plot, the observables of a cloud (:func:`cloud_arrays`), indexed by
        (plot, tree id)."""
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

    def setting(self, assign: dict):
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

    def trace(self, trace_part: dict):
        """The key, the pulses with hits and their hits for the trace-side parameters ``trace_part``.

        The search renders every stored-hit candidate on its baseline's trace and visits
        trace-side values one after the other (their features are cached separately); the cache
        (:class:`TraceCache`) holds the baseline's trace and the last other one, and reads back
        from disk the traces a stage marked (:meth:`keep`) instead of tracing them again.
        """
        from vlsforest.sim import trace_hits

        key, sv, edits = self.setting(trace_part)
        pulses, hits = self.traces.get(key, lambda: trace_hits(self._scene_for(edits), sv, seed=self.seed,
                                                               workers=self.workers, region=self.region),
                                       json.dumps(trace_part))
        return key, pulses, hits

    def keep(self, assigns: list, spill: bool = True) -> None:
        """The traces of ``assigns`` are this stage's: traces on disk that are not are deleted,
        and (with ``spill``) these are written to disk when they leave memory."""
        self.traces.keep({self.trace_key(a) for a in assigns}, spill)

    def trace_key(self, assign: dict) -> str:
        """The key of the trace that ``assign`` renders from (its trace-side part's :meth:`setting`)."""
        return self.setting(trace_part(assign))[0]

    def holds_trace(self, assign: dict) -> bool:
        """Whether the trace that ``assign`` renders from is in memory (no new trace)."""
        return self.trace_key(assign) in self.traces

    def pin(self, assign: dict) -> None:
        """Keep the trace of ``assign`` (the search's baseline) cached until the next pin."""
        self.traces.pin(self.trace_key(assign))

    def features(self, assign: dict) -> pd.DataFrame:
        """The observables per tree of the simulation with ``assign`` (cached)."""
        from vlsforest.sim import hit_offsets, redetect

        key, sv, edits = self.setting(assign)
        if key not in self._sims:
            tkey, pulses, hits = self.trace(trace_part(assign))
            parts = dict(self.parts,
                         reflectance=np.clip(self.parts["reflectance"] * edits["reflectance_scale"], 0, 1))
            if "specularity" in edits:
                parts["specularity"] = np.full(len(parts["specularity"]), edits["specularity"])
                parts["shininess"] = np.full(len(parts["shininess"]), lib.SHININESS)
            if self._offsets[0] != tkey:  # the hits' index, kept for the trace rendered last
                self._offsets = (tkey, hit_offsets(pulses, hits))
            res = redetect(parts, pulses, hits, sv, seed=self.seed, hit_ptr=self._offsets[1])
            self.n_redetected += 1
            self._sims[key] = self.observables(cloud_arrays(res))
        return self._sims[key]


class Study:
    """All plots together: observables of real and simulated trees, cached per parameter set."""

    def __init__(self, setup: Setup, log, spill_dir: Path | None = None):
        self.plots = [PlotSim(p, setup.seed, setup.workers, log, setup.beam_sample_quality, spill_dir)
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
        """The simulated observables of every plot's trees with ``assign`` (cached)."""
        key = json.dumps(assign, sort_keys=True)
        if key not in self._cache:
            self._cache[key] = pd.concat([p.features(assign) for p in self.plots])
        return self._cache[key]

    def has_trace(self, assign: dict) -> bool:
        """Whether every plot holds the ray trace that ``assign`` renders from (no new trace)."""
        return all(p.holds_trace(assign) for p in self.plots)

    def residual(self, assign: dict) -> np.ndarray:
        """Real minus simulated observables (trees × :data:`~vlsforest.diagnose.features.FEATURES`)."""
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
