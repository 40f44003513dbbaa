"""The LiDAR simulator: HELIOS++ v1.0 pulse model on Embree, plus elliptical beams.

Public API
----------
- :class:`Scene` (``Scene.from_yaml``) — meshes, voxel sets, planes.
- :func:`load_survey` — SURVEY.yaml → :class:`Survey` (scanner preset + overrides, platform).
- :func:`simulate` — run a survey over a scene → :class:`SimulationResult`;
  :func:`simulate_to_las` — run it straight into a LAS/LAZ file, block by block.
- :func:`redetect` — re-run detection on stored sub-ray hits (:func:`hit_offsets` indexes
  them once for many re-detections); :func:`trace_hits` — trace and keep only those hits (no
  detection).
- :func:`write_points`, :func:`write_pulses`, :func:`save_hits`, :func:`load_hits`,
  :func:`load_pulses`, :func:`beam_geometry`; the outputs' documented suffixes.
- :data:`PRESETS`, :class:`ScannerSettings`.
"""

from vlsforest.sim.engine import DetectorOptions, SimulationResult, hit_offsets, redetect, simulate, trace_hits
from vlsforest.sim.output import (HITS_SUFFIXES, POINTS_SUFFIXES, PULSES_SUFFIXES, beam_geometry, load_hits,
                                  load_pulses, save_hits, simulate_to_las, write_points, write_pulses)
from vlsforest.sim.scanner import PRESETS, ScannerSettings
from vlsforest.sim.scene import Material, Scene
from vlsforest.sim.survey import Survey, load_survey, survey_from_dict

__all__ = [
    "Scene", "Material", "Survey", "load_survey", "survey_from_dict", "simulate", "simulate_to_las", "redetect",
    "hit_offsets", "trace_hits",
    "SimulationResult", "DetectorOptions", "write_points", "write_pulses", "save_hits", "load_hits",
    "load_pulses", "beam_geometry", "POINTS_SUFFIXES", "PULSES_SUFFIXES", "HITS_SUFFIXES",
    "PRESETS", "ScannerSettings",
]
