"""Object ids of a plot scene: the labels that tie a simulated return to its tree.

A simulated return carries the ``object_id`` of the scene part it hit. The ground plane is
:data:`GROUND_ID`, every surrounding (non-target) tree :data:`SURROUNDING_ID`, and target tree
``t`` (its segmented tree id, ≥ 1) has a stem ``10·t + 1`` and a crown ``10·t + 2``
(:func:`object_ids`), so extraction recovers the tree of each return from its id alone.
"""

from __future__ import annotations

from vlsforest.errors import ConfigError

__all__ = ["GROUND_ID", "SURROUNDING_ID", "object_ids"]

#: object id of the ground plane
GROUND_ID = 1
#: object id of all surrounding (non-target) trees
SURROUNDING_ID = 2


def object_ids(tree_id: int) -> tuple[int, int]:
    """Object ids of the stem and the crown of a target tree.

    Parameters
    ----------
    tree_id : int
        Segmented id of the target tree, ≥ 1.

    Returns
    -------
    tuple of int
        ``(10·tree_id + 1, 10·tree_id + 2)``: the stem's and the crown's object id.

    Raises
    ------
    ConfigError
        For a tree id below 1.
    """
    t = int(tree_id)
    if t <= 0:
        raise ConfigError(f"target tree ids must be positive, got {tree_id}")
    return 10 * t + 1, 10 * t + 2
