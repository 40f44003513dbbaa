"""Physics diagnosis: locate a sim-vs-real mismatch, name the missing physics, model it, check it.

Public API: :func:`diagnose` (run on a :class:`Setup`), :func:`load_setup` (read a sim-config
YAML), :data:`CANDIDATES` (the physics library), :func:`tree_features` and :data:`FEATURES`
(the per-tree observables). The command is ``vlsforest diagnose``.
"""

from vlsforest.diagnose.core import Setup, diagnose, load_setup
from vlsforest.diagnose.features import FEATURES, tree_features
from vlsforest.diagnose.library import CANDIDATES

__all__ = ["diagnose", "load_setup", "Setup", "CANDIDATES", "FEATURES", "tree_features"]
