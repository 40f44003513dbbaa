"""Physics diagnosis: locate a sim-vs-real mismatch, name the missing physics, model it, check it.

Public API: :func:`diagnose` (run on a :class:`Setup`), :func:`load_setup` (read a sim-config
YAML), :data:`CANDIDATES` (the physics library), :func:`tree_features` and :data:`FEATURES`
(the per-tree observables). The command is ``vlsforest diagnose``.

Modules: :mod:`.setup` (the sim-config and its schema), :mod:`.library` (the candidate physics),
:mod:`.features` (the observables), :mod:`.traces` (the ray-trace cache),
:mod:`.simulation` (real and simulated observables per plot), :mod:`.stats` (the statistics),
:mod:`.search` (locate, attribute, fit, check), :mod:`.truth` (a benchmark's reference),
:mod:`.report` (the report and verdict), :mod:`.run` (:func:`diagnose`), :mod:`.figure`.
"""

from vlsforest.diagnose.features import FEATURES, tree_features
from vlsforest.diagnose.library import CANDIDATES
from vlsforest.diagnose.run import diagnose
from vlsforest.diagnose.setup import PlotInput, Setup, load_setup

__all__ = ["diagnose", "load_setup", "Setup", "PlotInput", "CANDIDATES", "FEATURES", "tree_features"]
