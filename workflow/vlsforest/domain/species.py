"""Species, species groups and the PAD settings that follow the group.

The study sorts its trees into two groups, broadleaf and conifer; the leaf angle distribution
and PADmax used to estimate plant area density (and to scale voxels by it) follow the group
(Weiser et al. 2021: broadleaf planophile with PADmax 5 m²/m³, conifer erectophile with
PADmax 8 m²/m³). :data:`SPECIES_GROUPS` is the one species → group table of the package:
extraction, PAD validation, voxel models and statistics all read it through
:func:`species_group`.
"""

from __future__ import annotations

from types import MappingProxyType

from vlsforest.errors import ConfigError

__all__ = [
    "GROUPS",
    "DEFAULT_GROUP",
    "SPECIES_GROUPS",
    "PAD_GROUPS",
    "species_key",
    "species_group",
]

#: the species groups, in display order
GROUPS = ("broadleaf", "conifer")
#: group of a tree whose species is not given (a target without species, a surrounding tree)
DEFAULT_GROUP = "broadleaf"

#: species key → group: the study's target species (Fagus sylvatica, Carpinus betulus, Picea
#: abies), the surrounding species the tree generator models, two more species of the study
#: area, and each group name standing for itself (a field list may give only the group)
SPECIES_GROUPS = MappingProxyType({
    "fagus_sylvatica": "broadleaf",
    "carpinus_betulus": "broadleaf",
    "quercus_petraea": "broadleaf",
    "acer_pseudoplatanus": "broadleaf",
    "picea_abies": "conifer",
    "pinus_sylvestris": "conifer",
    "pseudotsuga_menziesii": "conifer",
    "abies_alba": "conifer",
    "broadleaf": "broadleaf",
    "conifer": "conifer",
})

#: per species group: leaf angle distribution (``lad``, one of
#: :data:`vlsforest.domain.leaf_angles.LAD_NAMES`) and PADmax in m²/m³ (``pad_max``)
PAD_GROUPS = MappingProxyType({
    "broadleaf": MappingProxyType({"lad": "planophile", "pad_max": 5.0}),
    "conifer": MappingProxyType({"lad": "erectophile", "pad_max": 8.0}),
})

_MISSING = object()


def species_key(species) -> str:
    """Normalised key of a species name.

    Parameters
    ----------
    species : str
        A species key (``"fagus_sylvatica"``) or Latin name (``"Fagus sylvatica"``).

    Returns
    -------
    str
        The name stripped, in lower case, with spaces replaced by underscores.
    """
    return str(species).strip().lower().replace(" ", "_")


def species_group(species, default=_MISSING) -> str:
    """Species group of a species.

    Parameters
    ----------
    species : str
        A species key or Latin name (see :func:`species_key`), or a group name.
    default : str, optional
        Group of a species that :data:`SPECIES_GROUPS` does not list. Without it such a
        species is an error.

    Returns
    -------
    str
        ``"broadleaf"`` or ``"conifer"`` (or ``default``).

    Raises
    ------
    ConfigError
        For a species not in :data:`SPECIES_GROUPS` when no ``default`` is given.
    """
    group = SPECIES_GROUPS.get(species_key(species))
    if group is not None:
        return group
    if default is _MISSING:
        raise ConfigError(f"unknown species {species!r}: give one of {sorted(SPECIES_GROUPS)}")
    return default
