"""LAS/LAZ input and output.

Point clouds travel through vlsforest as :class:`PointCloud`: float64 ``xyz`` plus a dict of
per-point attribute arrays named like laspy's dimensions (``intensity``, ``return_number``,
``number_of_returns``, ``gps_time``, ``point_source_id``, ``scan_angle`` in degrees,
``classification``) and any extra dimensions (``object_id``, ``amplitude``, ``tree_id`` …).

Files are written as LAS 1.4, point format 6 (LAZ when the name ends in ``.laz``) with a fixed
scale of 0.1 mm, an offset rounded to whole metres and a fixed header date (2021-01-01, or
``SOURCE_DATE_EPOCH`` when set), so that the same points give the same bytes.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass, field
from pathlib import Path

import laspy
import numpy as np

from vlsforest._memory import release_freed_memory
from vlsforest.errors import InputDataError
from vlsforest.io.atomic import atomic_path

#: standard point-format-6 dimensions that :func:`write_las` fills from ``PointCloud.attrs``
_STANDARD = {
    "intensity": np.uint16,
    "return_number": np.uint8,
    "number_of_returns": np.uint8,
    "gps_time": np.float64,
    "point_source_id": np.uint16,
    "classification": np.uint8,
    "user_data": np.uint8,
}
#: point format 6 flag fields packed into the byte ``classification_flags``: name → (bit, width)
_FLAGS = {"synthetic": (0, 1), "key_point": (1, 1), "withheld": (2, 1), "overlap": (3, 1),
          "scanner_channel": (4, 2), "scan_direction_flag": (6, 1), "edge_of_flight_line": (7, 1)}
_SCALE = 1e-4


@dataclass
class PointCloud:
    """Points with attributes.

    Parameters
    ----------
    xyz : ndarray, shape (n, 3), float64
        Coordinates.
    attrs : dict of str to ndarray
        Per-point attributes, each of length n.
    """

    xyz: np.ndarray
    attrs: dict = field(default_factory=dict)

    def __post_init__(self):
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        for k, v in self.attrs.items():
            if len(v) != len(self.xyz):
                raise InputDataError(f"attribute {k!r} has {len(v)} values for {len(self.xyz)} points")

    def __len__(self) -> int:
        return len(self.xyz)

    def subset(self, mask_or_index) -> "PointCloud":
        """Return the points selected by a boolean mask or an index array."""
        return PointCloud(self.xyz[mask_or_index], {k: v[mask_or_index] for k, v in self.attrs.items()})

    @staticmethod
    def concat(clouds: list["PointCloud"]) -> "PointCloud":
        """Concatenate clouds; attributes missing in any cloud are dropped."""
        clouds = list(clouds)
        if not clouds:
            return PointCloud(np.zeros((0, 3)))
        keys = set(clouds[0].attrs)
        for c in clouds[1:]:
            keys &= set(c.attrs)
        return PointCloud(
            np.concatenate([c.xyz for c in clouds]),
            {k: np.concatenate([c.attrs[k] for c in clouds]) for k in sorted(keys)},
        )


def read_las(path, require: tuple[str, ...] = (), allow_empty: bool = False) -> PointCloud:
    """Read a LAS/LAZ file.

    Parameters
    ----------
    path : str or Path
        The file.
    require : tuple of str
        Dimension names that must be present (standard or extra); a missing one is an error.
    allow_empty : bool
        Whether a file without points is acceptable.

    Returns
    -------
    PointCloud
        ``scan_angle`` is converted to degrees whatever the point format.

    Raises
    ------
    InputDataError
        When the file is missing, unreadable, empty, holds NaN/inf coordinates or lacks a
        required dimension. The message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputDataError(f"{path}: no such file")
    try:
        las = laspy.read(path)
    except Exception as exc:  # laspy/lazrs raise many types for corrupt data
        raise InputDataError(f"{path}: not a readable LAS/LAZ file ({' '.join(str(exc).split())})") from None
    _check_record_count(path, las.header)
    xyz = np.column_stack([np.asarray(las.x, float), np.asarray(las.y, float), np.asarray(las.z, float)])
    if len(xyz) == 0 and not allow_empty:
        raise InputDataError(f"{path}: the file holds no points")
    if not np.isfinite(xyz).all():
        raise InputDataError(f"{path}: {int((~np.isfinite(xyz)).any(axis=1).sum())} points have NaN or infinite coordinates")
    check_precision(path, xyz)
    names = set(las.point_format.dimension_names)
    missing = [r for r in require if r not in names]
    if missing:
        raise InputDataError(f"{path}: missing LAS dimension(s) {', '.join(missing)}")
    attrs = {}
    for name in las.point_format.dimension_names:
        if name in ("X", "Y", "Z"):
            continue
        arr = np.asarray(las[name])
        if name == "scan_angle":  # point formats 6-10: 0.006 degree units
            arr = arr.astype(np.float64) * 0.006
        elif name == "scan_angle_rank":
            arr = arr.astype(np.float64)
        attrs[name] = arr
    if "scan_angle" not in attrs and "scan_angle_rank" in attrs:
        attrs["scan_angle"] = attrs.pop("scan_angle_rank")
    return PointCloud(xyz, attrs)


#: the finest detail the analyses need (m); coordinates whose float64 spacing is coarser are refused
PRECISION_M = 0.01


def check_precision(path, xyz: np.ndarray) -> None:
    """Refuse coordinates so large that float64 cannot hold :data:`PRECISION_M` (1 cm) there.

    Raises
    ------
    InputDataError
        Naming the file, the largest coordinate and the resolution float64 has at it.
    """
    if len(xyz) == 0:
        return
    big = float(np.abs(xyz).max())
    step = float(np.spacing(big))
    if step > PRECISION_M:
        raise InputDataError(f"{path}: coordinates reach {big:.6g} m, where float64 resolves only {step:.3g} m "
                             f"(coarser than {PRECISION_M * 100:g} cm); shift the cloud towards the origin")


def _check_record_count(path: Path, header) -> None:
    """Warn when an uncompressed file holds more or fewer point records than its header says."""
    import warnings

    if header.are_points_compressed:
        return
    size = path.stat().st_size
    end = size
    start_evlr = getattr(header, "start_of_first_evlr", 0) or 0
    if start_evlr and header.number_of_evlrs:
        end = min(end, int(start_evlr))
    rec = header.point_format.size
    n_file = (end - int(header.offset_to_point_data)) // rec
    if n_file != header.point_count:
        warnings.warn(f"{path}: the header counts {header.point_count} points but the file holds "
                      f"{max(n_file, 0)} point records; read {min(header.point_count, max(n_file, 0))}",
                      DataWarning, stacklevel=3)


class DataWarning(UserWarning):
    """An input that is read, but whose inconsistency the user should know about."""


def _creation_date() -> datetime.date:
    """The header date: ``SOURCE_DATE_EPOCH`` if set, else a fixed date, so bytes are reproducible."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if epoch and epoch.isdigit():
        return datetime.datetime.fromtimestamp(int(epoch), tz=datetime.timezone.utc).date()
    return datetime.date(2021, 1, 1)


def write_las(path, cloud: PointCloud, extra: dict | None = None) -> Path:
    """Write a cloud as LAS 1.4 point format 6 (LAZ if ``path`` ends in ``.laz``).

    Parameters
    ----------
    path : str or Path
        Output file; parent folders are created.
    cloud : PointCloud
        Points. Standard attributes (``intensity``, ``return_number``, ``number_of_returns``,
        ``gps_time``, ``point_source_id``, ``classification``, ``user_data``, ``scan_angle`` in
        degrees) fill the standard fields; every other attribute becomes an extra dimension
        of its own dtype.
    extra : dict, optional
        Further extra dimensions (name to array).

    Returns
    -------
    Path
        The path written.
    """
    attrs = dict(cloud.attrs)
    if extra:
        attrs.update(extra)
    pieces = LasPieces(path)
    pieces.add(PointCloud(cloud.xyz, attrs))
    return pieces.write()


class LasPieces:
    """A LAS/LAZ file gathered piece by piece and written at once: the bytes :func:`write_las`
    writes for the pieces joined.

    Each piece's attributes are packed into point records when it is added (what a point keeps
    until the write: its float64 coordinates and its record, 62 bytes for a simulation's
    returns); the offsets, the whole metres below the smallest coordinate of all pieces, are
    known only at the write. Pieces beyond ``spill_bytes`` go to an unnamed temporary file in
    the output's folder (removed by the system when it is closed, also on a crash) as later
    pieces arrive, so a simulation holds about ``spill_bytes`` of returns however many it
    makes; the last piece added stays in memory, so a single piece is never copied to disk.
    The write places the coordinates piece by piece and hands the records to the writer one
    piece at a time.

    Parameters
    ----------
    path : str or Path
        The output file (LAZ if it ends in ``.laz``); written only by :meth:`write`.
    spill_bytes : int
        The bytes of pieces held in memory before the earlier ones go to the temporary file.
    """

    def __init__(self, path, spill_bytes: int = 128 << 20):
        self.path = Path(path)
        self._header = None
        self._dtypes = None
        self._pieces = []
        self._held = 0
        self._spill = None
        self._spilled = []  # the point count of each piece in the temporary file, in order
        self._spill_bytes = int(spill_bytes)
        self._lo = np.full(3, np.inf)
        self.n_points = 0

    def add(self, cloud: PointCloud) -> None:
        """Pack a piece's points into records (every piece has the first one's attributes)."""
        attrs = {k: np.asarray(v) for k, v in cloud.attrs.items()}
        dtypes = {k: v.dtype for k, v in attrs.items()}
        if self._header is None:
            self._header, self._dtypes = _las_header(attrs), dtypes
        elif dtypes != self._dtypes:
            raise ValueError(f"{self.path}: a piece with the attributes {dtypes}, the first had {self._dtypes}")
        if self._held > self._spill_bytes:
            self._spill_pieces()
        xyz = cloud.xyz
        if len(xyz):
            self._lo = np.minimum(self._lo, [xyz[:, k].min() for k in range(3)])  # per column: ≈ 10× faster
        rec = _las_records(self.path, self._header, attrs, len(xyz))
        self._pieces.append((xyz, rec))
        self._held += xyz.nbytes + rec.nbytes
        self.n_points += len(xyz)

    def _spill_pieces(self) -> None:
        """The pieces held in memory to the end of the temporary file."""
        import tempfile

        if self._spill is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._spill = tempfile.TemporaryFile(dir=self.path.parent, prefix=f".{self.path.name}.pieces-")
        for xyz, rec in self._pieces:
            self._spill.write(np.ascontiguousarray(xyz, dtype=np.float64).data)
            self._spill.write(rec.data)
            self._spilled.append(len(rec))
        self._pieces, self._held = [], 0
        release_freed_memory()

    def _read_spilled(self):
        """The temporary file's pieces, ``(xyz, records)`` in the order they were added."""
        f, dtype = self._spill, self._header.point_format.dtype()
        f.flush()
        f.seek(0)
        for n in self._spilled:
            xyz = np.empty((n, 3), dtype=np.float64)
            rec = np.empty(n, dtype=dtype)
            for buf in (xyz, rec):
                view = buf.view(np.uint8).reshape(-1)
                if f.readinto(view) != len(view):
                    raise OSError(f"{self.path}: the temporary file of its pieces ends early")
            yield xyz, rec

    def write(self) -> Path:
        """Write the file (whole or not at all) and return its path; the pieces are released."""
        if self._header is None:
            raise ValueError(f"{self.path}: no piece of points to write")
        header = self._header
        header.offsets = np.floor(self._lo) if self.n_points else np.zeros(3)
        try:
            _write_records(self.path, header, self._placed(header))
        finally:
            if self._spill is not None:
                self._spill.close()
            self._spill, self._spilled, self._pieces, self._held = None, [], [], 0
        return self.path

    def _placed(self, header):
        """Each piece's records with its coordinates placed, in the order added: the temporary
        file's pieces, then those in memory (each released once the writer has it)."""
        if self._spill is not None:
            for xyz, rec in self._read_spilled():
                _place_xyz(self.path, header, rec, xyz)
                yield rec
        freed = 0
        while self._pieces:
            xyz, rec = self._pieces.pop(0)
            _place_xyz(self.path, header, rec, xyz)
            yield rec
            freed += xyz.nbytes + rec.nbytes
            del xyz, rec
            if freed > 64 << 20:  # the written pieces' pages back to the system
                release_freed_memory()
                freed = 0


def _las_header(attrs: dict) -> laspy.LasHeader:
    """Point format 6 header, its extra dimensions those of ``attrs`` (offsets not yet set)."""
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.creation_date = _creation_date()
    header.generating_software = "vlsforest"
    header.system_identifier = "vlsforest"
    header.scales = np.array([_SCALE, _SCALE, _SCALE])
    for name, arr in attrs.items():
        if name in _STANDARD or name == "scan_angle" or name in _FLAGS:
            continue
        header.add_extra_dim(laspy.ExtraBytesParams(name=name, type=arr.dtype))
    return header


def _las_records(path: Path, header, attrs: dict, n: int) -> np.ndarray:
    """Point records of ``n`` points with every field but the coordinates filled from ``attrs``."""
    # the point records are filled field by field in one structured array (what laspy's
    # per-dimension setters produce, without their re-allocations and range checks)
    rec = np.zeros(n, dtype=header.point_format.dtype())
    bits = np.zeros(n, dtype=np.uint8)
    flags = np.zeros(n, dtype=np.uint8)
    for name, arr in attrs.items():
        if name in _FLAGS:
            bit, width = _FLAGS[name]
            flags |= (arr.astype(np.uint8) & ((1 << width) - 1)) << bit
        elif name == "scan_angle":
            rec["scan_angle"] = np.clip(np.round(arr / 0.006), -30000, 30000).astype(np.int16)
        elif name in ("return_number", "number_of_returns"):  # 4-bit fields of one byte
            v = arr.astype(np.uint8)
            if len(v) and v.max() > 15:
                raise InputDataError(f"{path}: {name} above 15 does not fit LAS point format 6")
            bits |= v << (0 if name == "return_number" else 4)
        elif name in _STANDARD:
            rec[name] = arr.astype(_STANDARD[name])
        else:
            rec[name] = arr
    rec["bit_fields"] = bits
    rec["classification_flags"] = flags
    return rec


def _place_xyz(path: Path, header, rec: np.ndarray, xyz: np.ndarray) -> None:
    """The coordinates into ``rec``, quantised with the header's offsets and scales."""
    lim = np.iinfo(np.int32)
    for i, ax in enumerate("XYZ"):
        q = np.round((xyz[:, i] - header.offsets[i]) / header.scales[i])
        if len(q) and (q.max() > lim.max or q.min() < lim.min):
            raise InputDataError(f"{path}: coordinates too far apart for the 0.1 mm LAS scale")
        rec[ax] = q


def _write_records(path: Path, header, pieces) -> None:
    """Write point records, given as an iterable of arrays, in one file (whole or not at all):
    the bytes of one write of the records joined."""
    # straight to the writer: a LasData would compute the header's bounds and counts a second time
    with atomic_path(path) as tmp, open(tmp, "wb+") as out, \
            laspy.LasWriter(out, header, do_compress=path.suffix.lower() == ".laz", closefd=False) as writer:
        deciding, n_written = [], 0
        for rec in pieces:
            if not len(rec):
                continue
            writer.write_points(laspy.PackedPointRecord(rec, header.point_format))
            deciding.append(_deciding_records(rec, header, first=not n_written))
            n_written += 1
        extra = writer.header.vlrs.get("ExtraBytesVlr")
        if n_written > 1 and extra:
            # laspy keeps the extra dimensions' statistics chunk by chunk: they are set again from
            # the records that decide them for the whole file, as one write of all records would
            extra[0].partial_reset()
            extra[0].grow(laspy.PackedPointRecord(np.concatenate(deciding), header.point_format))


def _deciding_records(rec: np.ndarray, header, first: bool) -> np.ndarray:
    """The records that decide the extra dimensions' statistics of a file: its first record
    (``first``) and, per extra dimension, the smallest and largest one."""
    at = [0] if first else []
    for name in header.point_format.extra_dimension_names:
        v = rec[name].reshape(len(rec), -1)
        at += [*v.argmin(axis=0).tolist(), *v.argmax(axis=0).tolist()]
    return rec[at]
