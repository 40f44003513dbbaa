"""TLS shots and their traversal of the voxel grid (Amanatides–Woo), with AMAPVox-style accumulators.

Shots
-----
A shot has an origin, a unit direction and its echoes (range along the beam, beam-fraction
weight, and whether it counts as a plant hit). :func:`load_tls_scans` reads a TLS folder::

    scan_{k}.laz            all returns; gps_time, return_number/number_of_returns
    scan_{k}.survey.yaml    the scan's survey (optional): every emitted pulse, empty ones included
    scans.csv               scan_id, x, y, z, …, gps_time_start (scanner positions); optional
                            beam_divergence_full_1e2_mrad, beam_exit_diameter_m, scanner

With a survey file, every shot of the scan pattern is rebuilt with
:meth:`vlsforest.sim.survey.Survey.pulses` and the echoes are matched to their pulse by GPS
time (the recorder writes ``pulse time + gps_time_start``). Without one (real data), shots are
the echo groups of equal GPS time, with the scanner position of ``scans.csv`` as origin; such
scans hold **no empty shots**, so beams that crossed a voxel without returning are missing and
PAD is biased high (mostly at the crown top and sky side). A scan whose position is unknown is
an :class:`~vlsforest.errors.InputDataError`.

**Shots blocked inside the minimum range.** A scanner records nothing closer than its minimum
range (1.5 m for the VZ-400). A shot that hits a branch or leaves within that range returns no
echo and looks exactly like a shot into the open sky; traversed as empty, it crosses every crown
behind the obstacle without a hit and pulls their PAD towards zero (on the default forest a
scanner 0.9 m from a small tree's foliage lost 90 % of its empty shots this way, and a beech
crown behind it 80 % of its PAD). The scanner cannot see its own blind zone, but the other scans
can: every echo of every scan within ``range_min + blind_radius`` of a scanner position is
collected, and an empty shot whose first ``range_min`` metres pass within ``blind_radius`` of one
of those echoes is taken as blocked there and left out (counted in :attr:`TlsScan.blind_shots`).
Scans without a minimum range, or without a survey file (no empty shots), are unchanged.

Echo weights: echo k of an n-echo shot intercepts 1/n of the beam (AMAPVox "rank" weights with
the equal table). Echoes of the ``ground_classes`` (class 2 by default) stop the beam but are
not plant hits: their free path counts as transmitted.

Traversal and accumulators (per crossed voxel, per shot)
--------------------------------------------------------
The grid is one global lattice: cell (i, j, k) spans ``origin + [i, i+1)·s`` per axis. A shot
enters through the grid's bounding box (or starts in the cell of its origin), and crosses cells
in order; an echo at range r belongs to the cell whose parameter interval ``(t_in, t_out]``
holds r (an echo on a shared face belongs to the cell the ray leaves). In each cell, the free
paths are one per echo (length ``r − t_in``, the echo's weight) plus the exiting remainder
(length ``l = t_out − t_in``) when more than 1e-5 of the beam is left. The beam section at the
cell centre is ``S = π (tan(δ/2)·d + D0/2)²`` (δ the full divergence at 1/e², D0 the exit
diameter, d the range of the cell centre), as in AMAPVox's laser specification (its VZ-400 entry:
D0 = 7 mm, δ = 0.35 mrad). δ and D0 are the scanner's: with a survey file its scanner's datasheet
beam (``2 × divergence_mrad`` and ``exit_diameter_m`` of its
:class:`~vlsforest.sim.scanner.Beam`); without one the ``scans.csv`` columns
``beam_divergence_full_1e2_mrad`` and ``beam_exit_diameter_m``, defaulting to those of the preset
named in its ``scanner`` column, else of the study's ``riegl_vz400``. With δ = D0 = 0, S = 1. Accumulated per voxel (see :class:`Accumulators`):
shot count, potential path length, zenith angles, entering and intercepted beam section, the
FPL sums ``Σ bf·S·l_eff`` (all free paths and hits only) with the finite-leaf effective length
``l_eff = −ln(1 − λ₁ z)/λ₁``, λ₁ = 0.25·mean_leaf_area/V, and, for voxels holding plant echoes,
a histogram over the exit lengths of the transmittance records ``(bsIn, l_exit)`` on which the
numerical transmittance is solved (:mod:`vlsforest.pad.estimate`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from numba import njit

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.csvfile import read_csv_table

#: beam fraction below which a shot is considered fully intercepted
_RESIDUAL_MIN = 1e-5
#: number of exit-length bins of the transmittance records (over [0, s·√3])
N_LENGTH_BINS = 24
_SCAN_FILE = re.compile(r"^scan_(\d+)\.(laz|las)$", re.IGNORECASE)


# --------------------------------------------------------------------------- shots


@dataclass(eq=False)
class TlsScan:
    """The shots of one TLS scan.

    Attributes
    ----------
    scan_id : int
    source : str
        The point file.
    origin : ndarray, shape (n, 3)
        Shot origins.
    direction : ndarray, shape (n, 3)
        Unit shot directions.
    shot_ptr : ndarray of int64, shape (n + 1,)
        Echoes of shot s are ``shot_ptr[s]:shot_ptr[s+1]``, sorted by range.
    echo_range : ndarray, shape (m,)
        Distance from the shot origin along the direction (m).
    echo_weight : ndarray, shape (m,)
        Beam fraction intercepted by each echo (1/n for an n-echo shot).
    echo_hit : ndarray of bool, shape (m,)
        Whether the echo is a plant hit (False for ground-class echoes).
    beam_divergence_rad : float
        Full beam divergence δ (0 = unknown).
    exit_diameter_m : float
        Beam diameter at the exit D0 (0 = unknown).
    empty_shots : bool
        True when the shots come from the scan pattern (empty shots included).
    range_min_m : float
        The scanner's minimum range (0 = none or unknown).
    blind_shots : int
        Empty shots left out as blocked inside the minimum range (see the module docstring).
    """

    scan_id: int
    source: str
    origin: np.ndarray
    direction: np.ndarray
    shot_ptr: np.ndarray
    echo_range: np.ndarray
    echo_weight: np.ndarray
    echo_hit: np.ndarray
    beam_divergence_rad: float = 0.0
    exit_diameter_m: float = 0.0
    empty_shots: bool = False
    range_min_m: float = 0.0
    blind_shots: int = 0

    @property
    def n_shots(self) -> int:
        return len(self.direction)

    @property
    def n_echoes(self) -> int:
        return len(self.echo_range)

    def echo_shot(self) -> np.ndarray:
        """Shot index of every echo."""
        return np.repeat(np.arange(self.n_shots), np.diff(self.shot_ptr))

    def echo_xyz(self) -> np.ndarray:
        """Echo positions ``origin + range·direction``, shape (m, 3)."""
        s = self.echo_shot()
        return self.origin[s] + self.echo_range[:, None] * self.direction[s]


def _scan_files(tls_dir: Path) -> list[tuple[int, Path]]:
    out = []
    for p in tls_dir.iterdir():
        m = _SCAN_FILE.match(p.name)
        if m and p.is_file():
            out.append((int(m.group(1)), p))
    out.sort()
    ids = [k for k, _ in out]
    if len(set(ids)) != len(ids):
        raise InputDataError(f"{tls_dir}: two point files share a scan id ({ids})")
    return out


def _read_scans_csv(path: Path) -> pd.DataFrame | None:
    if not path.is_file():
        return None
    return read_csv_table(path, "scan table", ("scan_id",)).set_index("scan_id")


def _row(table: pd.DataFrame | None, scan_id: int):
    if table is None or scan_id not in table.index:
        return None
    r = table.loc[scan_id]
    if isinstance(r, pd.DataFrame):
        r = r.iloc[0]
    return r


def _csr(shot_of_echo: np.ndarray, rng: np.ndarray, n_shots: int):
    """Sort echoes by (shot, range) and build the CSR pointer."""
    order = np.lexsort((rng, shot_of_echo))
    counts = np.bincount(shot_of_echo, minlength=n_shots)
    ptr = np.zeros(n_shots + 1, np.int64)
    np.cumsum(counts, out=ptr[1:])
    return order, ptr, counts


def _weights(ptr: np.ndarray, counts: np.ndarray) -> np.ndarray:
    n = np.repeat(counts, counts).astype(np.float64)
    return 1.0 / n if len(n) else np.zeros(0)


def _shots_from_survey(cloud, yaml_path: Path, row, las_path: Path, ground_classes) -> TlsScan:
    from vlsforest.sim.survey import load_survey

    survey = load_survey(yaml_path)  # errors name the file and the key
    if survey.platform_type != "static":
        raise InputDataError(f"{yaml_path}: not a static (TLS) survey")
    if row is None or "gps_time_start" not in row.index or not np.isfinite(float(row["gps_time_start"])):
        raise InputDataError(
            f"{las_path}: scans.csv gives no gps_time_start for this scan; it is needed to match echoes to shots"
        )
    pulses = survey.pulses(0, survey.n_slots)
    t_shot = pulses.gps_time + float(row["gps_time_start"])
    n = len(pulses)
    if "gps_time" not in cloud.attrs:
        raise InputDataError(f"{las_path}: no gps_time; echoes cannot be matched to shots")
    t = np.asarray(cloud.attrs["gps_time"], dtype=np.float64)
    tol = 0.25 / survey.scanner.emitter.prf_hz
    j = np.clip(np.searchsorted(t_shot, t), 1, max(n - 1, 1))
    if n == 1:
        j = np.zeros(len(t), np.int64)
        best = j
    else:
        left, right = j - 1, j
        best = np.where(np.abs(t_shot[left] - t) <= np.abs(t_shot[right] - t), left, right)
    miss = np.abs(t_shot[best] - t) > tol if n else np.ones(len(t), bool)
    if np.any(miss):
        raise InputDataError(
            f"{las_path}: {int(miss.sum())} of {len(t)} echoes match no shot of {yaml_path.name} by GPS time "
            f"(tolerance {tol:.3g} s)"
        )
    o, d = pulses.origin[best], pulses.direction[best]
    rng = np.einsum("ij,ij->i", cloud.xyz - o, d)
    order, ptr, counts = _csr(best, rng, n)
    hit = _hit_mask(cloud, ground_classes)
    beam = survey.scanner.beam
    div = 2.0 * float(beam.divergence_mrad[0]) * 1e-3  # the 1/e² half angle → full
    return TlsScan(scan_id=0, source=str(las_path), origin=pulses.origin.astype(np.float64),
                   direction=pulses.direction.astype(np.float64), shot_ptr=ptr,
                   echo_range=rng[order], echo_weight=_weights(ptr, counts), echo_hit=hit[order],
                   beam_divergence_rad=div, exit_diameter_m=float(beam.exit_diameter_m),
                   empty_shots=True,
                   range_min_m=float(survey.scanner.detector.range_min_m))


def _hit_mask(cloud, ground_classes) -> np.ndarray:
    if ground_classes and "classification" in cloud.attrs:
        return ~np.isin(np.asarray(cloud.attrs["classification"]), np.asarray(list(ground_classes)))
    return np.ones(len(cloud), bool)


def _shots_from_points(cloud, row, las_path: Path, ground_classes) -> TlsScan:
    pos = None
    if row is not None and all(c in row.index for c in ("x", "y", "z")):
        pos = np.array([float(row["x"]), float(row["y"]), float(row["z"])])
        if not np.all(np.isfinite(pos)):
            pos = None
    if pos is None:
        raise InputDataError(
            f"{las_path}: the scanner position of this scan is unknown (no scans.csv row with x, y, z); "
            "PAD needs the origin of every shot"
        )
    if "gps_time" in cloud.attrs:
        _, shot = np.unique(np.asarray(cloud.attrs["gps_time"], dtype=np.float64), return_inverse=True)
    else:  # every point is its own single-echo shot
        shot = np.arange(len(cloud))
    shot = shot.astype(np.int64).ravel()
    n = int(shot.max()) + 1 if len(shot) else 0
    v = cloud.xyz - pos
    rng = np.sqrt(np.einsum("ij,ij->i", v, v))
    if np.any(rng <= 0):
        raise InputDataError(f"{las_path}: a point lies exactly at the scanner position")
    order, ptr, counts = _csr(shot, rng, n)
    last = order[ptr[1:] - 1]  # farthest echo of each shot gives the direction
    direction = v[last] / rng[last, None]
    div, d0 = scan_beam(row, las_path)
    return TlsScan(scan_id=0, source=str(las_path), origin=np.broadcast_to(pos, (n, 3)).copy(),
                   direction=direction, shot_ptr=ptr, echo_range=rng[order],
                   echo_weight=_weights(ptr, counts), echo_hit=_hit_mask(cloud, ground_classes)[order],
                   beam_divergence_rad=div, exit_diameter_m=d0, empty_shots=False)


#: the scanner preset whose beam a scans.csv row without beam columns or ``scanner`` gets
DEFAULT_TLS_SCANNER = "riegl_vz400"


def scan_beam(row, source) -> tuple[float, float]:
    """The beam of one scan from its ``scans.csv`` row: (full 1/e² divergence in rad, exit
    diameter in m); missing columns come from the preset in the ``scanner`` column, else
    :data:`DEFAULT_TLS_SCANNER`.

    Raises
    ------
    InputDataError
        A value that is not a finite number ≥ 0, or an unknown ``scanner`` (naming ``source``).
    """
    from vlsforest.sim.scanner import PRESETS

    name = DEFAULT_TLS_SCANNER
    if row is not None and "scanner" in row.index and isinstance(row["scanner"], str) and row["scanner"]:
        name = row["scanner"]
        if name not in PRESETS:
            raise InputDataError(f"{source}: scans.csv names an unknown scanner {name!r} "
                                 f"(known: {', '.join(sorted(PRESETS))})")
    pre = PRESETS[name]
    vals = {"beam_divergence_full_1e2_mrad": 2.0 * pre.beam.divergence_mrad[0],
            "beam_exit_diameter_m": pre.beam.exit_diameter_m}
    for key in vals:
        if row is not None and key in row.index and not pd.isna(row[key]):
            try:
                v = float(row[key])
            except (TypeError, ValueError):
                v = float("nan")
            if not (math.isfinite(v) and v >= 0):
                raise InputDataError(f"{source}: scans.csv column {key} must be a number ≥ 0 (got {row[key]!r})")
            vals[key] = v
    return vals["beam_divergence_full_1e2_mrad"] * 1e-3, vals["beam_exit_diameter_m"]


def _drop_blind_shots(scans: list[TlsScan], radius: float, step: float = 0.02) -> None:
    """Leave out the empty shots blocked inside their scanner's minimum range (in place)."""
    from scipy.spatial import cKDTree

    if radius <= 0:
        return
    todo = [sc for sc in scans if sc.empty_shots and sc.range_min_m > 0 and sc.n_shots]
    if not todo:
        return
    echoes = np.concatenate([sc.echo_xyz() for sc in scans if sc.n_echoes] or [np.zeros((0, 3))])
    if len(echoes) == 0:
        return
    near_trees = {}  # (position, reach) → KD-tree of the echoes within reach; tilted scans share positions

    def near_tree(o, reach):
        key = (*o.tolist(), reach)
        if key not in near_trees:
            dv = echoes - o
            near = echoes[np.einsum("ij,ij->i", dv, dv) <= reach * reach]
            near_trees[key] = cKDTree(near) if len(near) else None
        return near_trees[key]

    for sc in todo:
        empty = np.flatnonzero(np.diff(sc.shot_ptr) == 0)
        if len(empty) == 0:
            continue
        blocked = np.zeros(len(empty), bool)
        origins, which = np.unique(sc.origin[empty], axis=0, return_inverse=True)
        which = which.reshape(-1)
        r = np.arange(step / 2, sc.range_min_m, step)
        for k, o in enumerate(origins):
            tree = near_tree(o, sc.range_min_m + radius)
            if tree is None:
                continue
            sel = np.flatnonzero(which == k)
            for c0 in range(0, len(sel), 20000):
                part = sel[c0:c0 + 20000]
                pts = o + sc.direction[empty[part]][:, None, :] * r[None, :, None]
                d, _ = tree.query(pts.reshape(-1, 3), k=1, distance_upper_bound=radius, workers=-1)
                blocked[part] = np.isfinite(d).reshape(len(part), len(r)).any(axis=1)
        if not blocked.any():
            continue
        keep = np.ones(sc.n_shots, bool)
        keep[empty[blocked]] = False  # no echoes: dropping them leaves every echo's order intact
        sc.origin, sc.direction = sc.origin[keep], sc.direction[keep]
        sc.shot_ptr = np.concatenate([[0], sc.shot_ptr[1:][keep]])
        sc.blind_shots = int(blocked.sum())


def load_tls_scans(tls_dir, ground_classes=(2,), scan_ids=None, blind_radius: float = 0.04) -> list[TlsScan]:
    """Read the shots of every scan of a TLS folder.

    Parameters
    ----------
    tls_dir : str or Path
        Folder with ``scan_{k}.laz`` (or ``.las``), optionally ``scan_{k}.survey.yaml`` and
        ``scans.csv`` (see the module docstring).
    ground_classes : iterable of int
        LAS classes whose echoes stop the beam without counting as plant hits.
    scan_ids : iterable of int, optional
        Only these scans.
    blind_radius : float
        An empty shot passing this close to an echo of any scan within its scanner's minimum
        range is left out as blocked there (module docstring); 0 keeps every empty shot.

    Returns
    -------
    list of TlsScan
        In scan id order.

    Raises
    ------
    InputDataError
        Missing folder or point files, unreadable files, echoes that match no shot, or a scan
        without a known scanner position (the message names the scan's file).
    """
    from vlsforest.io.las import read_las

    if isinstance(blind_radius, bool) or not isinstance(blind_radius, (int, float)) \
            or not math.isfinite(blind_radius) or blind_radius < 0:
        raise ConfigError(f"blind_radius: must be a number >= 0, got {blind_radius!r}")
    tls_dir = Path(tls_dir)
    if not tls_dir.is_dir():
        raise InputDataError(f"{tls_dir}: no such TLS folder")
    files = _scan_files(tls_dir)
    if scan_ids is not None:
        want = {int(k) for k in scan_ids}
        files = [(k, p) for k, p in files if k in want]
    if not files:
        raise InputDataError(f"{tls_dir}: no scan_{{k}}.laz point files")
    table = _read_scans_csv(tls_dir / "scans.csv")
    scans = []
    for k, path in files:
        cloud = read_las(path, allow_empty=True)
        row = _row(table, k)
        yml = tls_dir / f"scan_{k}.survey.yaml"
        if yml.is_file():
            sc = _shots_from_survey(cloud, yml, row, path, ground_classes)
        else:
            sc = _shots_from_points(cloud, row, path, ground_classes)
        sc.scan_id = k
        scans.append(sc)
    _drop_blind_shots(scans, float(blind_radius))
    return scans


# --------------------------------------------------------------------------- grid


def grid_for_scans(scans, cell_size: float = 0.25, extent=None, pad_cells: int = 1):
    """Grid origin and shape covering the plant echoes (and the scanners) of the scans.

    Parameters
    ----------
    scans : list of TlsScan
    cell_size : float
    extent : (xmin, ymin, xmax, ymax), optional
        Horizontal extent; echoes outside it are ignored for sizing. Default: the echoes' bbox.
    pad_cells : int
        Cells added above the highest echo.

    Returns
    -------
    origin : ndarray (3,)
        Multiple of ``cell_size`` on every axis.
    shape : tuple of int
    """
    s = _check_cell_size(cell_size)
    pts = [sc.echo_xyz() for sc in scans if sc.n_echoes]
    if not pts:
        raise InputDataError("the scans hold no echoes; the grid cannot be sized")
    xyz = np.concatenate(pts)
    if extent is not None:
        ext = np.asarray(extent, dtype=float).reshape(-1)
        if ext.shape != (4,) or not np.all(np.isfinite(ext)) or ext[2] <= ext[0] or ext[3] <= ext[1]:
            raise ConfigError(f"extent: expected xmin ymin xmax ymax with xmin < xmax, ymin < ymax, got {extent!r}")
        inside = (xyz[:, 0] >= ext[0]) & (xyz[:, 0] <= ext[2]) & (xyz[:, 1] >= ext[1]) & (xyz[:, 1] <= ext[3])
        if not inside.any():
            raise InputDataError(f"no echo lies inside the extent {list(ext)}")
        zlo, zhi = xyz[inside, 2].min(), xyz[inside, 2].max()
        lo = np.array([ext[0], ext[1], zlo])
        hi = np.array([ext[2], ext[3], zhi])
    else:
        lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    lo_i = np.floor(lo / s + 1e-9).astype(np.int64)
    hi_i = np.floor(hi / s).astype(np.int64) + 1
    hi_i[2] += int(pad_cells)
    origin = lo_i * s
    shape = tuple(int(v) for v in hi_i - lo_i)
    return origin.astype(float), shape


def _check_cell_size(cell_size) -> float:
    try:
        s = float(cell_size)
    except (TypeError, ValueError):
        raise ConfigError(f"voxel_size: must be a positive number, got {cell_size!r}") from None
    if not (math.isfinite(s) and s > 0):
        raise ConfigError(f"voxel_size: must be a positive number, got {cell_size!r}")
    return s


# --------------------------------------------------------------------------- accumulators


@dataclass(eq=False)
class Accumulators:
    """Per-voxel sums of the traversal, dense arrays of shape ``shape``.

    Attributes
    ----------
    origin : ndarray (3,)
        Lower corner of cell (0, 0, 0) (a multiple of ``cell_size``).
    cell_size : float
    shape : tuple (nx, ny, nz)
    nb_sampling : int32
        Shots crossing the voxel (AMAPVox ``nbSampling``).
    nb_echos : int32
        Plant echoes in the voxel (``nbEchos``).
    lg_total : float64
        Σ potential path length l (``lgTotal``).
    angle_sum : float64
        Σ raw zenith angle, degrees 0–180 (``angleMean`` = angle_sum / nb_sampling).
    angle_sum_folded : float64
        Σ zenith angle folded into [0, 90] per shot.
    bs_entering, bs_intercepted : float64
        E = Σ bf·S over the free paths, I = Σ over plant hits of bf·S.
    leff_sum, leff_hit_sum : float64
        Σ bf·S·l_eff over all free paths / over plant hits (FPL estimators).
    bsl_exit : float64
        Σ bsIn·l_exit over the transmittance records.
    slot : int32
        Row of the voxel in ``hist`` (−1: none; only voxels holding plant echoes have one).
    hist : float64, shape (n_slots, N_LENGTH_BINS, 2)
        Per exit-length bin: Σ bsIn and Σ bsIn·l_exit (transmittance records).
    n_shots, n_echoes : int
        Shots traversed and echoes read.
    empty_shots : bool
        Whether every scan included its empty shots.
    """

    origin: np.ndarray
    cell_size: float
    shape: tuple
    nb_sampling: np.ndarray
    nb_echos: np.ndarray
    lg_total: np.ndarray
    angle_sum: np.ndarray
    angle_sum_folded: np.ndarray
    bs_entering: np.ndarray
    bs_intercepted: np.ndarray
    leff_sum: np.ndarray
    leff_hit_sum: np.ndarray
    bsl_exit: np.ndarray
    slot: np.ndarray
    hist: np.ndarray
    n_shots: int = 0
    n_echoes: int = 0
    empty_shots: bool = True
    mean_leaf_area: float = 0.0
    info: dict = field(default_factory=dict)

    def angle_mean(self, folded: bool = False) -> np.ndarray:
        """Mean zenith angle per voxel (degrees; NaN where unsampled)."""
        a = self.angle_sum_folded if folded else self.angle_sum
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.nb_sampling > 0, a / np.maximum(self.nb_sampling, 1), np.nan)

    def centres(self, ijk) -> np.ndarray:
        """World coordinates of cell centres."""
        return self.origin + (np.asarray(ijk, dtype=float) + 0.5) * self.cell_size


def _new_accumulators(origin, s, shape, n_slots) -> Accumulators:
    n = int(np.prod(shape))
    z = lambda dt=np.float64: np.zeros(n, dt)  # noqa: E731
    return Accumulators(origin=np.asarray(origin, float), cell_size=float(s), shape=tuple(shape),
                        nb_sampling=z(np.int32), nb_echos=z(np.int32), lg_total=z(), angle_sum=z(),
                        angle_sum_folded=z(), bs_entering=z(), bs_intercepted=z(), leff_sum=z(),
                        leff_hit_sum=z(), bsl_exit=z(), slot=np.full(n, -1, np.int32),
                        hist=np.zeros((n_slots, N_LENGTH_BINS, 2)))


@njit(cache=True)
def _leff(z, lam):
    if lam <= 0.0:
        return z
    x = lam * z
    if x >= 1.0:
        x = 1.0 - 1e-12
    return -math.log1p(-x) / lam


@njit(cache=True)
def _traverse(origin, direction, shot_ptr, erange, eweight, ehit, g0, s, nx, ny, nz, tan_half, d0_half, lam,
              slot, hist, lbin, nb_samp, nb_echo, lg_tot, th_raw, th_fold, bs_ent, bs_int, s_leff,
              s_leff_hit, bsl_exit):
    """Traverse every shot; add to the flat accumulators. Returns the number of voxel crossings."""
    n_shots = direction.shape[0]
    nbins = hist.shape[1]
    lo = np.empty(3)
    hi = np.empty(3)
    nn = np.empty(3, np.int64)
    nn[0], nn[1], nn[2] = nx, ny, nz
    for a in range(3):
        lo[a] = g0[a]
        hi[a] = g0[a] + nn[a] * s
    use_s = tan_half > 0.0 or d0_half > 0.0
    crossings = 0
    o = np.empty(3)
    d = np.empty(3)
    idx = np.empty(3, np.int64)
    tnext = np.empty(3)
    for sh in range(n_shots):
        for a in range(3):
            o[a] = origin[sh, a]
            d[a] = direction[sh, a]
        dz = min(1.0, max(-1.0, d[2]))
        theta = math.degrees(math.acos(dz))
        thf = 180.0 - theta if theta > 90.0 else theta
        # slab test
        tmin = -np.inf
        tmax = np.inf
        ok = True
        for a in range(3):
            if d[a] != 0.0:
                t1 = (lo[a] - o[a]) / d[a]
                t2 = (hi[a] - o[a]) / d[a]
                if t1 > t2:
                    t1, t2 = t2, t1
                if t1 > tmin:
                    tmin = t1
                if t2 < tmax:
                    tmax = t2
            elif o[a] < lo[a] or o[a] >= hi[a]:
                ok = False
        if not ok or tmax <= tmin or tmax <= 0.0:
            continue
        t0 = tmin if tmin > 0.0 else 0.0
        e = shot_ptr[sh]
        eend = shot_ptr[sh + 1]
        bf = 1.0
        while e < eend and erange[e] <= t0:  # echoes before the grid
            bf -= eweight[e]
            e += 1
        if bf <= _RESIDUAL_MIN:
            continue
        for a in range(3):
            p = o[a] + t0 * d[a]
            c = int(math.floor((p - lo[a]) / s))
            if c < 0:
                c = 0
            elif c >= nn[a]:
                c = nn[a] - 1
            idx[a] = c
            if d[a] > 0.0:
                tnext[a] = (lo[a] + (c + 1) * s - o[a]) / d[a]
            elif d[a] < 0.0:
                tnext[a] = (lo[a] + c * s - o[a]) / d[a]
            else:
                tnext[a] = np.inf
        tcur = t0
        while True:
            texit = min(tnext[0], min(tnext[1], tnext[2]))
            if texit < tcur:
                texit = tcur
            l = texit - tcur
            wsum = 0.0
            hit_w = 0.0
            n_hit = 0
            leff_all = 0.0
            leff_hit = 0.0
            len_nonhit = 0.0
            n_nonhit = 0
            while e < eend and erange[e] <= texit:
                w = eweight[e]
                zfp = erange[e] - tcur
                if zfp < 0.0:
                    zfp = 0.0
                le = _leff(zfp, lam)
                wsum += w
                leff_all += w * le
                if ehit[e]:
                    n_hit += 1
                    hit_w += w
                    leff_hit += w * le
                else:
                    len_nonhit += zfp
                    n_nonhit += 1
                e += 1
            rem = bf - wsum
            bsin = wsum
            if rem > _RESIDUAL_MIN:
                bsin = bf
                leff_all += rem * _leff(l, lam)
                len_nonhit += l
                n_nonhit += 1
            if l > 0.0 or wsum > 0.0:
                v = (idx[0] * ny + idx[1]) * nz + idx[2]
                S = 1.0
                if use_s:
                    cx = lo[0] + (idx[0] + 0.5) * s - o[0]
                    cy = lo[1] + (idx[1] + 0.5) * s - o[1]
                    cz = lo[2] + (idx[2] + 0.5) * s - o[2]
                    r = tan_half * math.sqrt(cx * cx + cy * cy + cz * cz) + d0_half
                    S = math.pi * r * r
                lexit = len_nonhit / n_nonhit if n_nonhit > 0 else l
                nb_samp[v] += 1
                nb_echo[v] += n_hit
                lg_tot[v] += l
                th_raw[v] += theta
                th_fold[v] += thf
                bs_ent[v] += bsin * S
                bs_int[v] += hit_w * S
                s_leff[v] += leff_all * S
                s_leff_hit[v] += leff_hit * S
                bsl_exit[v] += bsin * S * lexit
                sl = slot[v]
                if sl >= 0:
                    b = int(lexit / lbin)
                    if b >= nbins:
                        b = nbins - 1
                    hist[sl, b, 0] += bsin * S
                    hist[sl, b, 1] += bsin * S * lexit
                crossings += 1
            bf = rem
            if bf <= _RESIDUAL_MIN:
                break
            out = False
            for a in range(3):
                if tnext[a] == texit:
                    if d[a] > 0.0:
                        idx[a] += 1
                        tnext[a] = (lo[a] + (idx[a] + 1) * s - o[a]) / d[a]
                    else:
                        idx[a] -= 1
                        tnext[a] = (lo[a] + idx[a] * s - o[a]) / d[a]
                    if idx[a] < 0 or idx[a] >= nn[a]:
                        out = True
            if out:
                break
            tcur = texit
    return crossings


def _hit_voxels(scans, origin, s, shape) -> np.ndarray:
    """Flat indices of the voxels holding plant echoes (echo nudged back along its beam)."""
    keys = []
    shape = np.asarray(shape)
    for sc in scans:
        if not sc.n_echoes:
            continue
        sh = sc.echo_shot()[sc.echo_hit]
        p = sc.origin[sh] + (sc.echo_range[sc.echo_hit] - 1e-7)[:, None] * sc.direction[sh]
        c = np.floor((p - origin) / s).astype(np.int64)
        ok = np.all((c >= 0) & (c < shape), axis=1)
        c = c[ok]
        keys.append((c[:, 0] * shape[1] + c[:, 1]) * shape[2] + c[:, 2])
    if not keys:
        return np.zeros(0, np.int64)
    return np.unique(np.concatenate(keys))


def accumulate(scans, origin, cell_size: float, shape, mean_leaf_area: float | None = 0.01,
               exit_diameter_m: float | None = None) -> Accumulators:
    """Traverse every shot of the scans through the grid and sum the per-voxel accumulators.

    Parameters
    ----------
    scans : list of TlsScan
        From :func:`load_tls_scans`.
    origin : array_like (3,)
        Lower corner of cell (0, 0, 0); should be a multiple of ``cell_size`` (global lattice).
    cell_size : float
        Voxel edge (m).
    shape : (nx, ny, nz)
    mean_leaf_area : float or None
        Mean one-sided area of a leaf (m²) for the finite-leaf effective free path of the FPL
        estimators (AMAPVox default 0.01); None or 0: turbid medium (l_eff = l).
    exit_diameter_m : float, optional
        Beam diameter at the exit D0 (overrides the scans' value).

    Returns
    -------
    Accumulators
    """
    s = _check_cell_size(cell_size)
    origin = np.asarray(origin, dtype=float).reshape(-1)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise ConfigError(f"origin: expected three finite numbers, got {origin!r}")
    try:
        shape = tuple(int(v) for v in shape)
    except (TypeError, ValueError):
        raise ConfigError(f"shape: expected three positive integers, got {shape!r}") from None
    if len(shape) != 3 or min(shape) < 1:
        raise ConfigError(f"shape: expected three positive integers, got {shape!r}")
    mla = 0.0 if mean_leaf_area is None else float(mean_leaf_area)
    if not (math.isfinite(mla) and mla >= 0):
        raise ConfigError(f"mean_leaf_area: must be a non-negative number, got {mean_leaf_area!r}")
    lam = 0.25 * mla / s ** 3
    if lam * s * math.sqrt(3.0) >= 1.0:
        raise ConfigError(
            f"mean_leaf_area: {mla} m² is too large for {s} m voxels (needs 0.25·a·√3·s/V < 1)"
        )
    scans = list(scans)
    hv = _hit_voxels(scans, origin, s, shape)
    acc = _new_accumulators(origin, s, shape, len(hv))
    acc.slot[hv] = np.arange(len(hv), dtype=np.int32)
    acc.mean_leaf_area = mla
    lbin = s * math.sqrt(3.0) / N_LENGTH_BINS
    crossings = 0
    for sc in scans:
        if sc.n_shots == 0:
            continue
        d0 = sc.exit_diameter_m if exit_diameter_m is None else float(exit_diameter_m)
        crossings += _traverse(
            np.ascontiguousarray(sc.origin, dtype=np.float64), np.ascontiguousarray(sc.direction, dtype=np.float64),
            sc.shot_ptr.astype(np.int64), sc.echo_range.astype(np.float64), sc.echo_weight.astype(np.float64),
            sc.echo_hit.astype(np.bool_), origin, s, shape[0], shape[1], shape[2],
            math.tan(0.5 * sc.beam_divergence_rad), 0.5 * d0, lam, acc.slot, acc.hist, lbin,
            acc.nb_sampling, acc.nb_echos, acc.lg_total, acc.angle_sum, acc.angle_sum_folded, acc.bs_entering,
            acc.bs_intercepted, acc.leff_sum, acc.leff_hit_sum, acc.bsl_exit)
        acc.n_shots += sc.n_shots
        acc.n_echoes += sc.n_echoes
        acc.empty_shots = acc.empty_shots and sc.empty_shots
    for name in ("nb_sampling", "nb_echos", "lg_total", "angle_sum", "angle_sum_folded", "bs_entering",
                 "bs_intercepted", "leff_sum", "leff_hit_sum", "bsl_exit", "slot"):
        setattr(acc, name, getattr(acc, name).reshape(shape))
    acc.info = {"crossings": int(crossings), "n_scans": len(scans), "n_hit_voxels": int(len(hv))}
    return acc


__all__ = ["TlsScan", "Accumulators", "load_tls_scans", "grid_for_scans", "accumulate", "N_LENGTH_BINS"]
