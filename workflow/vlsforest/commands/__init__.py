"""Sub-commands of the ``vlsforest`` CLI, one module per stage (see :mod:`vlsforest.cli`)."""
