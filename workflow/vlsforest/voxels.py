"""Voxel models of tree crowns: fixed-size occupancy cubes and PAD-scaled cubes (the study's Table 2).

Every model lives on one **global lattice** per cell size ``a0``: cell ``(i, j, k)`` spans
``[i·a0, (i+1)·a0)`` on each axis in world coordinates (cell corners at integer multiples of the
size), so models of different methods of one plot share their cells and the 0.25 m PAD grid,
the scaled cubes and the CoG shifts all refer to the same cells.

Methods are registered by *kind* (:func:`register_method`); the workflow config names a method
and gives its kind and parameters::

    methods:
      fixed_0.25:          {kind: fixed, voxel_size: 0.25}
      scaled:              {kind: scaled, a0: 0.25, alpha: 0.5}
      scaled_random_shift: {kind: scaled, shift: random}
      scaled_cog_shift:    {kind: scaled, shift: cog}

Built-in kinds:

``fixed``
    a cube of side ``voxel_size`` for every cell holding at least ``min_points`` TLS points
    (default 1);
``scaled``
    the PAD-scaled cubes of HELIOS++/the study: side ``a = a0 · (PAD / PADmax)^alpha`` with PAD
    clipped to ``[0, PADmax]`` first (PADmax per voxel, from the species of the tree that owns
    the voxel), centred in the cell (``shift: none``), moved per axis by ``U(−1, 1)·(a0 − a)/2``
    (``shift: random``, seeded) or moved towards the centre of gravity of the cell's TLS points
    and clamped so that the cube stays in its cell (``shift: cog``). Cells whose PAD is 0 carry no
    cube. Cells that hold TLS points but whose PAD is *flagged* (too few shots for an estimate,
    see :mod:`vlsforest.pad`) take the median PAD of the sampled voxels of the same tree
    (``flagged: median``, default), or the tree's PADmax (``flagged: pad_max``), or are dropped
    (``flagged: drop``); the count of such cells is reported.

A new method is one function registered here (or in a module the workflow imports), one rule
file and one config entry — see docs/tutorials/adding-a-method.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from vlsforest.domain.cubes import scaled_cubes
from vlsforest.domain.leaf_angles import g_function
from vlsforest.domain.species import DEFAULT_GROUP, PAD_GROUPS
from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.voxel_model import VoxelModel

#: method kinds → builder functions ``f(inputs: ModelInputs, **params) -> VoxelModel``
METHOD_KINDS: dict[str, Callable] = {}


def register_method(kind: str):
    """Decorator registering a voxel-method builder under ``kind``.

    The builder is called as ``f(inputs, **params)`` with a :class:`ModelInputs` and the method's
    config entry (without ``kind``) and returns a :class:`VoxelModel`.
    """

    def deco(func):
        METHOD_KINDS[kind] = func
        return func

    return deco


@dataclass
class PadGrid:
    """Plant area density per cell of the PAD lattice (from :mod:`vlsforest.pad`).

    Attributes
    ----------
    size : float
        Cell size of the PAD grid (the study: 0.25 m).
    ijk : ndarray int64 (m, 3)
        Cells with an estimate or a flag, global lattice.
    transmittance : ndarray (m,)
        Transmittance per metre (AMAPVox ``transmittance``) or NaN.
    angle_deg : ndarray (m,)
        Mean zenith angle of the shots through the cell (degrees, AMAPVox ``angleMean``).
    sampled : ndarray bool (m,)
        False where the cell was crossed by too few shots (flagged; PAD not estimated).
    attenuation : ndarray (m,) or None
        Attenuation coefficient k = G·PAD of the FPL estimator (used with ``estimator: fpl_unbiased``).
    """

    size: float
    ijk: np.ndarray
    transmittance: np.ndarray
    angle_deg: np.ndarray
    sampled: np.ndarray
    attenuation: np.ndarray | None = None

    @classmethod
    def from_vox(cls, path, min_pulses: int = 5) -> "PadGrid":
        """Read a PAD grid from an AMAPVox ``.vox`` (columns ``transmittance``, ``angleMean``,
        ``nbSampling``; optional ``attenuation``, ``attenuationBiasCorrection`` and
        ``angleMeanFolded``, which :mod:`vlsforest.pad` writes and G is then evaluated at).

        Cells are placed on the global lattice: ``min_corner`` must be a multiple of ``res``.
        Cells crossed by fewer than ``min_pulses`` shots are not sampled.
        """
        from vlsforest.io.vox import read_vox

        vox = read_vox(path)
        need = {"transmittance", "angleMean", "nbSampling"}
        if not need <= set(vox.columns):
            raise InputDataError(f"{path}: a PAD grid needs columns {sorted(need)}")
        base = vox.min_corner / vox.res
        if np.abs(base - np.round(base)).max() > 1e-6:
            raise InputDataError(f"{path}: min_corner {vox.min_corner.tolist()} is not on the global "
                                 f"{vox.res} m lattice (a multiple of the cell size)")
        ijk = vox.ijk.astype(np.int64) + np.round(base).astype(np.int64)
        att = None
        if "attenuation" in vox.columns:
            att = np.asarray(vox.column("attenuation"), dtype=np.float64)
            if "attenuationBiasCorrection" in vox.columns:
                att = att - np.asarray(vox.column("attenuationBiasCorrection"), dtype=np.float64)
        n = np.asarray(vox.column("nbSampling"), dtype=np.float64)
        angle = "angleMeanFolded" if "angleMeanFolded" in vox.columns else "angleMean"
        return cls(float(vox.res), ijk, np.asarray(vox.column("transmittance"), dtype=np.float64),
                   np.asarray(vox.column(angle), dtype=np.float64), n >= min_pulses, att)


@dataclass
class ModelInputs:
    """What a voxel-method builder gets for one plot.

    Attributes
    ----------
    xyz : ndarray (n, 3)
        TLS points of the tree crowns to model (ground points and meshed stem points removed).
    owner : ndarray int64 (n,)
        Tree id per point.
    species_of : dict int → str
        Species group per tree id (``broadleaf`` or ``conifer``); trees not listed use ``default_group``.
    pad : PadGrid or None
        The plot's PAD grid (needed by scaled methods).
    seed : int
        Seed for random choices (random shift).
    default_group : str
        Species group of trees without one.
    """

    xyz: np.ndarray
    owner: np.ndarray
    species_of: dict
    pad: PadGrid | None = None
    seed: int = 0
    default_group: str = DEFAULT_GROUP


def cell_index(xyz, size: float) -> np.ndarray:
    """Global-lattice cell of each point (``floor(xyz / size)``)."""
    if not (np.isfinite(size) and size > 0):
        raise ConfigError(f"voxel size must be > 0, got {size!r}")
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(xyz).all():
        raise InputDataError("point coordinates contain NaN or infinite values")
    return np.floor(xyz / size).astype(np.int64)


def _group_cells(ijk: np.ndarray):
    """Unique cells (lexicographic order) and the inverse index of each row.

    The rows are packed into one mixed-radix ``int64`` key (same lexicographic order), which
    sorts about ten times faster than ``np.unique(axis=0)``; lattices too large for one key
    fall back to the row-wise unique.
    """
    ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
    if len(ijk) == 0:
        return ijk.copy(), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    lo = ijk.min(axis=0)
    ext = ijk.max(axis=0) - lo + 1
    if float(ext[0]) * float(ext[1]) * float(ext[2]) >= 2.0 ** 62:
        cells, inv, counts = np.unique(ijk, axis=0, return_inverse=True, return_counts=True)
        return cells, inv.reshape(-1), counts
    rel = ijk - lo
    key = (rel[:, 0] * ext[1] + rel[:, 1]) * ext[2] + rel[:, 2]
    ukey, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    cells = np.empty((len(ukey), 3), dtype=np.int64)
    cells[:, 2] = ukey % ext[2]
    rest = ukey // ext[2]
    cells[:, 1] = rest % ext[1]
    cells[:, 0] = rest // ext[1]
    return cells + lo, inv.reshape(-1), counts


def _majority(inv: np.ndarray, labels: np.ndarray, n_cells: int) -> np.ndarray:
    """Per cell, the label most rows carry (ties → the smallest label)."""
    labs, lab_idx = np.unique(labels, return_inverse=True)
    pair = inv.astype(np.int64) * len(labs) + lab_idx.reshape(-1)
    upair, cnt = np.unique(pair, return_counts=True)
    cell = upair // len(labs)
    lab = upair % len(labs)
    # sort by cell, then count descending, then label ascending: first row per cell wins
    order = np.lexsort((lab, -cnt, cell))
    cell_s, lab_s = cell[order], lab[order]
    first = np.ones(len(cell_s), dtype=bool)
    first[1:] = cell_s[1:] != cell_s[:-1]
    out = np.zeros(n_cells, dtype=np.int64)
    out[cell_s[first]] = labs[lab_s[first]]
    return out


def fixed_voxels(xyz, size: float, owner=None, min_points: int = 1) -> VoxelModel:
    """Occupancy cubes: every lattice cell holding at least ``min_points`` points.

    Parameters
    ----------
    xyz : ndarray (n, 3)
        Points.
    size : float
        Cell size (m), > 0.
    owner : ndarray (n,), optional
        Tree id per point (majority per cell); default all 0.
    min_points : int
        Minimum number of points in a filled cell (≥ 1).

    Returns
    -------
    VoxelModel
    """
    if int(min_points) != min_points or min_points < 1:
        raise ConfigError(f"min_points must be an integer ≥ 1, got {min_points!r}")
    ijk = cell_index(xyz, size)
    if len(ijk) == 0:
        raise InputDataError("no points to voxelise (empty tree or crown)")
    owner = np.zeros(len(ijk), dtype=np.int64) if owner is None else np.asarray(owner, dtype=np.int64)
    cells, inv, counts = _group_cells(ijk)
    own = _majority(inv, owner, len(cells))
    keep = counts >= min_points
    return VoxelModel(float(size), cells[keep], own[keep])


def shift_cubes(ijk, half, a0: float, mode: str = "none", seed: int = 0, cog=None) -> np.ndarray:
    """Centres of scaled cubes in their cells.

    Parameters
    ----------
    ijk : ndarray (n, 3)
        Cells on the ``a0`` lattice.
    half : ndarray (n,)
        Half sides (≤ a0/2).
    mode : {'none', 'random', 'cog'}
        ``none``: cell centre; ``random``: ``c + U(−1, 1)·(a0/2 − half)`` per axis
        (``default_rng(seed)``); ``cog``: ``c + clip(cog − c, −(a0/2 − half), a0/2 − half)`` per
        axis (cells whose ``cog`` is NaN stay centred).
    cog : ndarray (n, 3), optional
        Centre of gravity of each cell's points (``cog`` mode).
    """
    ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
    half = np.asarray(half, dtype=np.float64)
    c = (ijk + 0.5) * a0
    room = np.maximum(0.5 * a0 - half, 0.0)[:, None]
    if mode == "none":
        return c
    if mode == "random":
        rng = np.random.default_rng(seed)
        return c + rng.uniform(-1.0, 1.0, size=c.shape) * room
    if mode == "cog":
        if cog is None:
            raise ConfigError("shift 'cog' needs the centre of gravity of each cell's points")
        d = np.asarray(cog, dtype=np.float64) - c
        d = np.where(np.isfinite(d), d, 0.0)
        return c + np.clip(d, -room, room)
    raise ConfigError(f"shift must be one of 'none', 'random', 'cog', got {mode!r}")


def cell_centroids(xyz, size: float, cells) -> np.ndarray:
    """Mean of the points in each of ``cells`` (NaN for cells without points)."""
    ijk = cell_index(xyz, size)
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    out = np.full((len(cells), 3), np.nan)
    if len(ijk) == 0 or len(cells) == 0:
        return out
    ucells, inv, counts = _group_cells(ijk)
    sums = np.zeros((len(ucells), 3))
    np.add.at(sums, inv, np.asarray(xyz, dtype=np.float64))
    means = sums / counts[:, None]
    pos = _lookup(ucells, cells)
    ok = pos >= 0
    out[ok] = means[pos[ok]]
    return out


def _keys(ijk: np.ndarray, lo: np.ndarray) -> np.ndarray:
    """One int64 per cell, relative to the corner cell ``lo`` (extent < 2^21 cells per axis)."""
    off = np.asarray(ijk, dtype=np.int64) - lo
    if len(off) and (off.max() >= 2 ** 21 or off.min() < 0):
        raise InputDataError("voxel cells span more than 2^21 cells on an axis — the data cover too "
                             "large an area for this cell size")
    return (off[:, 0] << 42) | (off[:, 1] << 21) | off[:, 2]


def _lookup(table_cells: np.ndarray, query_cells: np.ndarray) -> np.ndarray:
    """Row of each query cell in ``table_cells`` (−1 if absent)."""
    table_cells = np.asarray(table_cells, dtype=np.int64).reshape(-1, 3)
    query_cells = np.asarray(query_cells, dtype=np.int64).reshape(-1, 3)
    out = np.full(len(query_cells), -1, dtype=np.int64)
    if len(table_cells) == 0 or len(query_cells) == 0:
        return out
    lo = table_cells.min(axis=0)
    hi = table_cells.max(axis=0)
    inside = np.all((query_cells >= lo) & (query_cells <= hi), axis=1)
    tk = _keys(table_cells, lo)
    qk = _keys(query_cells[inside], lo)
    order = np.argsort(tk, kind="stable")
    tks = tk[order]
    pos = np.minimum(np.searchsorted(tks, qk), len(tks) - 1)
    found = tks[pos] == qk
    idx = np.flatnonzero(inside)
    out[idx[found]] = order[pos[found]]
    return out


def pad_per_voxel(pad: PadGrid, owner, species_of: dict, default_group: str = DEFAULT_GROUP,
                  groups: dict | None = None, estimator: str = "transmittance"):
    """PAD of each cell of a PAD grid with the leaf angle distribution and PADmax of its owner's species group.

    Parameters
    ----------
    pad : PadGrid
        The cells and their transmittance (or attenuation) and mean shot angle.
    owner : ndarray int64 (m,)
        Tree id per cell.
    species_of : dict int → str
        Species group per tree id; trees not listed are in ``default_group``.
    default_group : str
        Group of the trees ``species_of`` does not list.
    groups : dict, optional
        Group → ``{"lad": …, "pad_max": …}``; default
        :data:`vlsforest.domain.species.PAD_GROUPS`.
    estimator : {"transmittance", "fpl_unbiased"}
        Which column of the grid gives the attenuation.

    Returns
    -------
    values : ndarray (m,)
        PAD (m²/m³) clipped to PADmax; NaN where not sampled.
    pad_max : ndarray (m,)
    """
    groups = PAD_GROUPS if groups is None else groups
    owner = np.asarray(owner, dtype=np.int64)
    grp = np.array([species_of.get(int(o), default_group) for o in owner], dtype=object)
    unknown = set(grp.tolist()) - set(groups)
    if unknown:
        raise ConfigError(f"species group(s) {sorted(unknown)} have no leaf angle distribution/pad_max "
                          f"(known: {sorted(groups)})")
    pad_max = np.array([groups[g]["pad_max"] for g in grp], dtype=np.float64)
    g = np.empty(len(owner))
    for name in set(grp.tolist()):
        m = grp == name
        g[m] = g_function(np.asarray(pad.angle_deg)[m], groups[name]["lad"])
    if estimator == "transmittance":
        t = np.asarray(pad.transmittance, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            k = -np.log(t)
    elif estimator == "fpl_unbiased":
        if pad.attenuation is None:
            raise ConfigError("estimator 'fpl_unbiased' needs the PAD grid's attenuation column")
        k = np.maximum(np.asarray(pad.attenuation, dtype=np.float64), 0.0)
    else:
        raise ConfigError(f"estimator must be 'transmittance' or 'fpl_unbiased', got {estimator!r}")
    with np.errstate(divide="ignore", invalid="ignore"):
        val = k / g
    val = np.where(np.isposinf(val), pad_max, val)
    val = np.minimum(val, pad_max)
    val = np.where(np.asarray(pad.sampled, dtype=bool), val, np.nan)
    return val, pad_max


@register_method("fixed")
def fixed_model(inputs: ModelInputs, voxel_size: float = 0.25, min_points: int = 1) -> VoxelModel:
    """The study's fixed-size occupancy cubes (see :func:`fixed_voxels`)."""
    return fixed_voxels(inputs.xyz, float(voxel_size), inputs.owner, int(min_points))


@register_method("scaled")
def scaled_model(inputs: ModelInputs, a0: float = 0.25, alpha: float = 0.5, shift: str = "none",
                 flagged: str = "median", estimator: str = "transmittance", groups: dict | None = None,
                 min_points: int = 1) -> VoxelModel:
    """PAD-scaled cubes on the PAD grid's cells that hold crown points (see the module docstring)."""
    if inputs.pad is None:
        raise ConfigError("scaled voxels need a PAD grid (the plot's pad.vox)")
    if flagged not in ("median", "pad_max", "drop"):
        raise ConfigError(f"flagged must be 'median', 'pad_max' or 'drop', got {flagged!r}")
    if shift not in ("none", "random", "cog"):
        raise ConfigError(f"shift must be one of 'none', 'random', 'cog', got {shift!r}")
    if abs(inputs.pad.size - a0) > 1e-9:
        raise ConfigError(f"a0 ({a0}) must equal the PAD grid's cell size ({inputs.pad.size})")
    occ = fixed_voxels(inputs.xyz, a0, inputs.owner, min_points)
    pos = _lookup(inputs.pad.ijk, occ.ijk)
    sub = PadGrid(a0, occ.ijk, np.full(occ.n_voxels, np.nan), np.full(occ.n_voxels, 90.0),
                  np.zeros(occ.n_voxels, dtype=bool),
                  None if inputs.pad.attenuation is None else np.full(occ.n_voxels, np.nan))
    ok = pos >= 0
    sub.transmittance[ok] = np.asarray(inputs.pad.transmittance)[pos[ok]]
    sub.angle_deg[ok] = np.asarray(inputs.pad.angle_deg)[pos[ok]]
    sub.sampled[ok] = np.asarray(inputs.pad.sampled, dtype=bool)[pos[ok]]
    if sub.attenuation is not None:
        sub.attenuation[ok] = np.asarray(inputs.pad.attenuation)[pos[ok]]
    pad, pad_max = pad_per_voxel(sub, occ.owner, inputs.species_of, inputs.default_group, groups, estimator)
    unsampled = ~np.isfinite(pad)
    if unsampled.any():
        if flagged == "pad_max":
            pad[unsampled] = pad_max[unsampled]
        elif flagged == "median":
            for o in np.unique(occ.owner[unsampled]):
                m_tree = occ.owner == o
                vals = pad[m_tree & ~unsampled]
                fill = float(np.median(vals)) if len(vals) else float(np.nanmedian(pad)) if (~unsampled).any() else 0.0
                pad[m_tree & unsampled] = fill
    half = scaled_cubes(occ.ijk, pad, pad_max, a0, alpha)
    keep = half > 0
    occ = occ.subset(keep)
    half, pad = half[keep], np.where(np.isfinite(pad[keep]), pad[keep], 0.0)
    if occ.n_voxels == 0:
        raise InputDataError("scaled voxels: every crown cell has PAD 0 — nothing to model")
    cog = cell_centroids(inputs.xyz, a0, occ.ijk) if shift == "cog" else None
    centre = shift_cubes(occ.ijk, half, a0, shift, inputs.seed, cog)
    return VoxelModel(a0, occ.ijk, occ.owner, half, centre, pad)


def build_model(method: dict, inputs: ModelInputs, name: str = "method") -> VoxelModel:
    """Build the voxel model of one configured method.

    Parameters
    ----------
    method : dict
        Config entry with ``kind`` and the kind's parameters.
    inputs : ModelInputs
    name : str
        Method name (for error messages).
    """
    if not isinstance(method, dict) or "kind" not in method:
        raise ConfigError(f"methods.{name}: needs a 'kind' ({', '.join(sorted(METHOD_KINDS))})")
    kind = method["kind"]
    if kind not in METHOD_KINDS:
        raise ConfigError(f"methods.{name}.kind: unknown kind {kind!r} (registered: {sorted(METHOD_KINDS)})")
    params = {k: v for k, v in method.items() if k not in ("kind", "description")}
    check_method_keys(METHOD_KINDS[kind], params, f"methods.{name}", kind)
    return METHOD_KINDS[kind](inputs, **params)


def check_method_keys(func, params: dict, where: str, kind: str) -> None:
    """Refuse keys that a method kind's function does not take, and missing required ones.

    The keys are compared with the function's signature (its first parameter takes the
    :class:`ModelInputs`), so a method registered from elsewhere is checked the same way.

    Raises
    ------
    ConfigError
        Naming the config entry, the key and the keys the kind takes.
    """
    import inspect

    sig = list(inspect.signature(func).parameters.values())[1:]
    if any(p.kind is p.VAR_KEYWORD for p in sig):
        return
    known = [p.name for p in sig if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))} for kind {kind!r} "
                          f"(it takes {', '.join(known) or 'no keys'})")
    missing = [p.name for p in sig if p.name in known and p.default is p.empty and p.name not in params]
    if missing:
        raise ConfigError(f"{where}: kind {kind!r} needs the key(s) {', '.join(missing)}")
    for p in sig:  # a value of another type than the key's default (a number, a name)
        if p.name not in params or p.default is p.empty or p.default is None:
            continue
        v, d = params[p.name], p.default
        number = isinstance(d, (int, float)) and not isinstance(d, bool)
        if number and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise ConfigError(f"{where}.{p.name}: must be a number, got {v!r}")
        if isinstance(d, str) and not isinstance(v, str):
            raise ConfigError(f"{where}.{p.name}: must be a name (text), got {v!r}")


__all__ = [
    "METHOD_KINDS",
    "ModelInputs",
    "PadGrid",
    "build_model",
    "cell_centroids",
    "cell_index",
    "fixed_voxels",
    "pad_per_voxel",
    "register_method",
    "shift_cubes",
]
