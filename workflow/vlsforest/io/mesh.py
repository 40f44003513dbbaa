"""Triangle meshes: reading Wavefront OBJ and PLY, writing OBJ and binary PLY.

Only geometry is read: vertex positions and faces (polygons are fan-triangulated in file order:
``(v0, v1, v2), (v0, v2, v3), ...``). Texture coordinates, normals, materials, groups and any
other PLY properties or elements are skipped.

The parsers are written for speed on large files: the OBJ reader sorts lines by their keyword
and hands the vertex and face blocks to pandas' C parser, the PLY reader maps binary data onto
NumPy structured dtypes. When the fast path fails, a slow line-by-line pass finds the first bad
line for the error message.
"""

from __future__ import annotations

import io
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlsforest.errors import InputDataError
from vlsforest.io.atomic import write_bytes


@dataclass(eq=False)
class TriangleMesh:
    """A triangle mesh.

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
        Vertex positions (float64).
    faces : array_like, shape (m, 3)
        Vertex indices of each triangle, 0-based (int32).
    """

    vertices: np.ndarray
    faces: np.ndarray

    def __post_init__(self):
        v = np.asarray(self.vertices, dtype=np.float64)
        if v.size == 0:
            v = v.reshape(0, 3)
        f = np.asarray(self.faces)
        if f.size == 0:
            f = f.reshape(0, 3)
        if v.ndim != 2 or v.shape[1] != 3:
            raise InputDataError(f"mesh vertices must have shape (n, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3:
            raise InputDataError(f"mesh faces must have shape (m, 3), got {f.shape}")
        if f.dtype.kind not in "iu":
            if not np.all(f == np.round(f)):
                raise InputDataError("mesh face indices must be whole numbers")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise InputDataError(f"mesh face index out of range 0..{len(v) - 1}")
        self.vertices = v
        self.faces = f.astype(np.int32)

    @property
    def n_vertices(self) -> int:
        """Number of vertices."""
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        """Number of triangles."""
        return len(self.faces)

    def bounds(self) -> np.ndarray:
        """Axis-aligned bounds of the vertices, shape (2, 3): ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``."""
        if len(self.vertices) == 0:
            return np.full((2, 3), np.nan)
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    def _cross(self) -> np.ndarray:
        a, b, c = (self.vertices[self.faces[:, n]] for n in range(3))
        return np.cross(b - a, c - a)

    def face_areas(self) -> np.ndarray:
        """Area of each triangle, shape (m,)."""
        return 0.5 * np.linalg.norm(self._cross(), axis=1)

    def face_normals(self) -> np.ndarray:
        """Unit normal of each triangle (right-hand rule on the vertex order), shape (m, 3).

        Degenerate (zero-area) triangles get a zero vector.
        """
        cr = self._cross()
        norm = np.linalg.norm(cr, axis=1, keepdims=True)
        return np.divide(cr, norm, out=np.zeros_like(cr), where=norm > 0)

    def area(self) -> float:
        """Total surface area."""
        return float(self.face_areas().sum())

    def translate(self, offset) -> "TriangleMesh":
        """Return a copy moved by ``offset`` (3,)."""
        offset = np.asarray(offset, dtype=np.float64).reshape(3)
        return TriangleMesh(self.vertices + offset, self.faces.copy())


# ====================================================================== reading
def read_mesh(path) -> TriangleMesh:
    """Read a triangle mesh from ``.obj`` or ``.ply`` (ASCII, binary little or big endian).

    Parameters
    ----------
    path : str or Path
        The file; the format is chosen by the extension (case-insensitive).

    Returns
    -------
    TriangleMesh

    Raises
    ------
    InputDataError
        Missing file, unknown extension, malformed lines (with the line number), no faces,
        face indices out of range, NaN or infinite vertex coordinates. The message names the file.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in (".obj", ".ply"):
        raise InputDataError(f"{path}: unknown mesh format {path.suffix!r} (use .obj or .ply)")
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputDataError(f"{path}: mesh file not found") from None
    except OSError as e:
        raise InputDataError(f"{path}: cannot read mesh file ({e})") from None
    if not raw.strip():
        raise InputDataError(f"{path}: mesh file is empty")
    if ext == ".obj":
        verts, polys = _read_obj(path, raw)
    else:
        verts, polys = _read_ply(path, raw)
    return _finish(path, verts, polys)


def _finish(path, verts: np.ndarray, tris: np.ndarray) -> TriangleMesh:
    if len(tris) == 0:
        raise InputDataError(f"{path}: mesh has no faces")
    bad = ~np.all(np.isfinite(verts), axis=1)
    if bad.any():
        raise InputDataError(
            f"{path}: vertex {int(np.argmax(bad)) + 1} has a NaN or infinite coordinate "
            f"({int(bad.sum())} such vertices)"
        )
    if tris.min() < 0 or tris.max() >= len(verts):
        bad_face = int(np.argmax(np.any((tris < 0) | (tris >= len(verts)), axis=1)))
        raise InputDataError(
            f"{path}: face index out of range in triangle {bad_face + 1}: {tris[bad_face].tolist()} "
            f"(0-based; the mesh has {len(verts)} vertices)"
        )
    return TriangleMesh(verts, tris.astype(np.int32))


def _fan(counts: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons given their vertex counts and concatenated indices, in order."""
    counts = np.asarray(counts, dtype=np.int64)
    ntri = counts - 2
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    total = int(ntri.sum())
    if total == 0:
        return np.zeros((0, 3), dtype=np.int64)
    poly = np.repeat(np.arange(len(counts)), ntri)
    tri_start = np.concatenate([[0], np.cumsum(ntri)[:-1]])
    j = np.arange(total) - tri_start[poly] + 1
    base = first[poly]
    return np.stack([flat[base], flat[base + j], flat[base + j + 1]], axis=1)


# ---------------------------------------------------------------------- OBJ
_OBJ_MAX_V = 7  # x y z [w] or x y z r g b [a]


def _read_obj(path, raw: bytes):
    if not raw.endswith(b"\n"):
        raw = raw + b"\n"
    b = np.frombuffer(raw, dtype=np.uint8)
    line_end = np.flatnonzero(b == 10)  # every line ends with '\n' (added above)
    line_start = np.concatenate([[0], line_end[:-1] + 1])
    c0 = b[line_start]
    c1 = b[np.minimum(line_start + 1, len(b) - 1)]
    c1 = np.where(line_start + 1 <= line_end, c1, 10)
    if np.any(((c0 == 32) | (c0 == 9)) & (line_end - line_start > 1)):
        # keywords after leading blanks: normalise those lines once (rare) and start again
        text = raw.decode("utf-8", errors="replace").split("\n")
        return _read_obj(path, "\n".join(s.lstrip(" \t") for s in text).encode("utf-8"))
    is_v = (c0 == ord("v")) & (c1 <= 32)  # 'v', not 'vt'/'vn'/'vp'
    is_f = (c0 == ord("f")) & (c1 <= 32)
    v_lines = np.flatnonzero(is_v)
    f_lines = np.flatnonzero(is_f)

    verts = _obj_vertices(path, raw, b, line_start, line_end, v_lines)
    if len(f_lines) == 0:
        raise InputDataError(f"{path}: OBJ file has no faces ('f' lines)")
    counts, flat, face_of = _obj_faces(path, raw, b, line_start, line_end, f_lines)
    # resolve 1-based and negative (relative to the vertices read so far) indices
    nb = np.searchsorted(v_lines, f_lines)[face_of]
    idx = np.where(flat < 0, nb + flat, flat - 1)
    bad = (flat == 0) | (idx < 0) | (idx >= len(verts))
    if bad.any():
        k = int(np.argmax(bad))
        raise InputDataError(
            f"{path}: line {int(f_lines[face_of[k]]) + 1}: face index {int(flat[k])} out of range "
            f"({len(verts)} vertices in the file, {int(nb[k])} before this line)"
        )
    return verts, _fan(counts, idx)


def _obj_block(b: np.ndarray, line_start, line_end, rows) -> bytes:
    """The selected lines without their one-letter keyword, each ending with '\\n'."""
    d = np.zeros(len(b) + 1, dtype=np.int8)
    d[line_start[rows] + 1] += 1
    d[line_end[rows] + 1] -= 1
    inside = np.cumsum(d[:-1], dtype=np.int8).astype(bool)
    return b[inside].tobytes()


def _obj_lines(raw: bytes, rows) -> list[tuple[int, str]]:
    text = raw.decode("utf-8", errors="replace").split("\n")
    return [(int(n) + 1, text[n]) for n in rows]


def _obj_vertices(path, raw, b, line_start, line_end, v_lines) -> np.ndarray:
    import pandas as pd

    if len(v_lines) == 0:
        return np.zeros((0, 3))
    block = _obj_block(b, line_start, line_end, v_lines)
    xyz = None
    try:
        df = pd.read_csv(
            io.BytesIO(block),
            sep=r"\s+",
            header=None,
            names=list(range(_OBJ_MAX_V)),
            dtype=np.float64,
            engine="c",
            keep_default_na=False,
            na_values=["", "nan", "NaN", "NAN"],  # '' marks a missing field
            skip_blank_lines=False,
            quoting=3,  # csv.QUOTE_NONE
        )
        xyz = df.to_numpy(dtype=np.float64)[:, :3]
    except (ValueError, pd.errors.ParserError):
        pass
    if xyz is None or xyz.shape != (len(v_lines), 3) or np.isnan(xyz).any():
        for ln, line in _obj_lines(raw, v_lines):
            parts = line.split()
            if len(parts) < 4:
                raise InputDataError(f"{path}: line {ln}: vertex needs x y z, got {line.strip()[:80]!r}")
            if len(parts) > _OBJ_MAX_V + 1:
                raise InputDataError(f"{path}: line {ln}: too many values on a vertex line")
            for p in parts[1:]:
                try:
                    x = float(p)
                except ValueError:
                    raise InputDataError(f"{path}: line {ln}: {p[:40]!r} is not a number") from None
                if np.isnan(x):
                    raise InputDataError(f"{path}: line {ln}: vertex has a NaN coordinate")
        raise InputDataError(f"{path}: could not parse the vertex lines")  # pragma: no cover
    return np.ascontiguousarray(xyz)


def _obj_faces(path, raw, b, line_start, line_end, f_lines):
    import pandas as pd

    from vlsforest.io._text import token_counts

    block = np.frombuffer(_obj_block(b, line_start, line_end, f_lines), dtype=np.uint8)
    # keep only the vertex index of a/b, a/b/c and a//c: drop every byte from a '/' to the token end
    slash = block == 47
    if slash.any():
        ws = block <= 32
        pos = np.arange(len(block), dtype=np.int64)
        last_ws = np.maximum.accumulate(np.where(ws, pos, -1))
        last_slash = np.maximum.accumulate(np.where(slash, pos, -1))
        token_start_slash = slash & np.concatenate([[True], ws[:-1]])
        if token_start_slash.any():
            return _obj_face_error(path, raw, f_lines)
        block = block[last_slash <= last_ws]
    bblock = block.tobytes()
    counts = token_counts(bblock)[: len(f_lines)]
    if np.any(counts < 3):
        n = int(f_lines[int(np.argmax(counts < 3))])
        line = raw[line_start[n] : line_end[n]].decode("utf-8", errors="replace")
        raise InputDataError(f"{path}: line {n + 1}: a face needs at least 3 vertices, got {line.strip()[:80]!r}")
    width = int(counts.max())
    arr = None
    try:
        df = pd.read_csv(
            io.BytesIO(bblock),
            sep=r"\s+",
            header=None,
            names=list(range(width)),
            dtype=np.float64,
            engine="c",
            keep_default_na=False,
            na_values=[""],  # '' marks the missing tail of a shorter polygon
            skip_blank_lines=False,
            quoting=3,  # csv.QUOTE_NONE
        )
        arr = df.to_numpy(dtype=np.float64)
    except (ValueError, pd.errors.ParserError):
        pass
    if arr is not None and arr.shape == (len(f_lines), width):
        vals = arr[np.arange(width)[None, :] < counts[:, None]]  # row-major: polygon by polygon
        if np.all(np.isfinite(vals)) and np.all(vals == np.round(vals)):
            return counts, vals.astype(np.int64), np.repeat(np.arange(len(f_lines)), counts)
    return _obj_face_error(path, raw, f_lines)


def _obj_face_error(path, raw, f_lines):
    for ln, line in _obj_lines(raw, f_lines):
        for tok in line.split()[1:]:
            try:
                int(tok.split("/", 1)[0])
            except ValueError:
                raise InputDataError(f"{path}: line {ln}: face vertex {tok[:40]!r} is not an integer index") from None
    raise InputDataError(f"{path}: could not parse the face lines")  # pragma: no cover


# ---------------------------------------------------------------------- PLY
_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclass
class _Prop:
    name: str
    dtype: str  # scalar type, or the item type of a list
    count_dtype: str | None = None  # set for list properties


@dataclass
class _Element:
    name: str
    count: int
    props: list


def _ply_header(path, raw: bytes):
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise InputDataError(f"{path}: not a PLY file (must start with 'ply' and have 'end_header')")
    nl = raw.find(b"\n", end)
    data_start = len(raw) if nl < 0 else nl + 1
    head_lines = raw[:end].decode("ascii", errors="replace").replace("\r", "").split("\n")
    fmt = None
    elements: list[_Element] = []
    for ln, line in enumerate(head_lines, 1):
        parts = line.split()
        if not parts or parts[0] in ("ply", "comment", "obj_info"):
            continue
        key = parts[0]
        if key == "format":
            if len(parts) < 2 or parts[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise InputDataError(f"{path}: line {ln}: unknown PLY format {line.strip()!r}")
            fmt = parts[1]
        elif key == "element":
            if len(parts) != 3:
                raise InputDataError(f"{path}: line {ln}: malformed element line {line.strip()!r}")
            try:
                count = int(parts[2])
            except ValueError:
                raise InputDataError(f"{path}: line {ln}: element count {parts[2]!r} is not an integer") from None
            if count < 0:
                raise InputDataError(f"{path}: line {ln}: negative element count")
            elements.append(_Element(parts[1], count, []))
        elif key == "property":
            if not elements:
                raise InputDataError(f"{path}: line {ln}: property before any element")
            if len(parts) == 5 and parts[1] == "list":
                if parts[2] not in _PLY_TYPES or parts[3] not in _PLY_TYPES:
                    raise InputDataError(f"{path}: line {ln}: unknown PLY type in {line.strip()!r}")
                if _PLY_TYPES[parts[2]][0] == "f":
                    raise InputDataError(f"{path}: line {ln}: a list count must be an integer type")
                elements[-1].props.append(_Prop(parts[4], _PLY_TYPES[parts[3]], _PLY_TYPES[parts[2]]))
            elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                elements[-1].props.append(_Prop(parts[2], _PLY_TYPES[parts[1]]))
            else:
                raise InputDataError(f"{path}: line {ln}: malformed property line {line.strip()!r}")
        else:
            raise InputDataError(f"{path}: line {ln}: unknown PLY header keyword {key!r}")
    if fmt is None:
        raise InputDataError(f"{path}: PLY header has no 'format' line")
    return fmt, elements, data_start, raw[:end].count(b"\n") + 1  # line number of 'end_header'


def _read_ply(path, raw: bytes):
    fmt, elements, data_start, header_lines = _ply_header(path, raw)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise InputDataError(f"{path}: PLY file has no 'vertex' element")
    vel = elements[names.index("vertex")]
    vprops = [p.name for p in vel.props]
    for c in "xyz":
        if c not in vprops:
            raise InputDataError(f"{path}: PLY vertex element has no property {c!r}")
    if "face" not in names or elements[names.index("face")].count == 0:
        raise InputDataError(f"{path}: mesh has no faces (PLY 'face' element missing or empty)")
    fel = elements[names.index("face")]
    fprop = [p for p in fel.props if p.count_dtype is not None and p.name in ("vertex_indices", "vertex_index")]
    if not fprop:
        raise InputDataError(f"{path}: PLY face element has no list property 'vertex_indices'")
    fname = fprop[0].name
    body = raw[data_start:]
    if fmt == "ascii":
        out = _ply_ascii(path, body, elements, header_lines)
    else:
        out = _ply_binary(path, body, elements, "<" if fmt == "binary_little_endian" else ">")
    v = out["vertex"]
    verts = np.stack([np.asarray(v[c], dtype=np.float64) for c in "xyz"], axis=1)
    counts, flat = out["face"][fname]
    if np.any(counts < 3):
        k = int(np.argmax(counts < 3))
        raise InputDataError(f"{path}: PLY face {k + 1} has {int(counts[k])} vertices (need at least 3)")
    return verts, _fan(counts, flat.astype(np.int64))


def _ply_binary(path, body: bytes, elements, endian: str) -> dict:
    pos = 0
    out = {}
    for el in elements:
        vals, pos = _ply_binary_element(path, body, pos, el, endian)
        if el.name in ("vertex", "face"):
            out[el.name] = vals
    return out


def _ply_binary_element(path, body: bytes, pos: int, el: _Element, endian: str):
    """Read one element; return ({prop: array or (counts, flat)}, new position)."""
    if el.count == 0:
        return {p.name: (np.zeros(0, np.int64), np.zeros(0, np.int64)) if p.count_dtype else np.zeros(0)
                for p in el.props}, pos
    # list lengths of the first row fix a candidate fixed-size row layout
    fields = []
    off = pos
    for p in el.props:
        if p.count_dtype is None:
            fields.append((p.name, endian + p.dtype))
            off += np.dtype(p.dtype).itemsize
        else:
            if off + np.dtype(p.count_dtype).itemsize > len(body):
                raise InputDataError(f"{path}: PLY data ends inside element {el.name!r}")
            k = int(np.frombuffer(body, endian + p.count_dtype, 1, off)[0])
            fields.append((p.name + "\0n", endian + p.count_dtype))
            off += np.dtype(p.count_dtype).itemsize
            if k:
                fields.append((p.name, endian + p.dtype, (k,)))
            off += k * np.dtype(p.dtype).itemsize
    dt = np.dtype(fields)
    need = dt.itemsize * el.count
    if pos + need <= len(body):
        rec = np.frombuffer(body, dt, el.count, pos)
        lists = [p for p in el.props if p.count_dtype is not None]
        ks = [dt.fields[p.name][0].shape[0] if p.name in dt.fields else 0 for p in lists]
        if all(np.all(rec[p.name + "\0n"] == k) for p, k in zip(lists, ks)):
            vals = {}
            for p, in_list in ((p, p.count_dtype is not None) for p in el.props):
                if not in_list:
                    vals[p.name] = rec[p.name].astype(np.float64 if p.dtype[0] == "f" else np.int64)
                else:
                    k = ks[lists.index(p)]
                    flat = rec[p.name].reshape(-1).astype(np.int64) if k else np.zeros(0, np.int64)
                    vals[p.name] = (np.full(el.count, k, dtype=np.int64), flat)
            return vals, pos + need
    # variable-length lists: walk row by row
    scal = {p.name: [] for p in el.props if p.count_dtype is None}
    lst = {p.name: ([], []) for p in el.props if p.count_dtype is not None}
    unpackers = {}
    for p in el.props:
        unpackers[p.name] = struct.Struct(endian + np.dtype(p.dtype).char)
        if p.count_dtype:
            unpackers[p.name + "\0n"] = struct.Struct(endian + np.dtype(p.count_dtype).char)
    try:
        for _ in range(el.count):
            for p in el.props:
                if p.count_dtype is None:
                    u = unpackers[p.name]
                    scal[p.name].append(u.unpack_from(body, pos)[0])
                    pos += u.size
                else:
                    uc = unpackers[p.name + "\0n"]
                    k = uc.unpack_from(body, pos)[0]
                    pos += uc.size
                    size = np.dtype(p.dtype).itemsize
                    if pos + k * size > len(body):
                        raise struct.error("short")
                    items = np.frombuffer(body, endian + p.dtype, k, pos)
                    pos += k * size
                    lst[p.name][0].append(k)
                    lst[p.name][1].append(items)
    except struct.error:
        raise InputDataError(f"{path}: PLY data ends inside element {el.name!r} (file truncated?)") from None
    vals = {n: np.asarray(v, dtype=np.float64) for n, v in scal.items()}
    for n, (ks, items) in lst.items():
        flat = np.concatenate(items).astype(np.int64) if items else np.zeros(0, np.int64)
        vals[n] = (np.asarray(ks, dtype=np.int64), flat)
    return vals, pos


def _ply_ascii(path, body: bytes, elements, header_lines: int) -> dict:
    text = body.decode("ascii", errors="replace")
    lines = [ln for ln in text.replace("\r", "").split("\n")]
    # skip blank lines while keeping line numbers
    numbered = [(n, ln) for n, ln in enumerate(lines, header_lines + 1) if ln.strip()]
    out = {}
    row = 0
    for el in elements:
        rows = numbered[row : row + el.count]
        if len(rows) < el.count:
            raise InputDataError(
                f"{path}: PLY element {el.name!r} needs {el.count} lines, the file ends after {len(rows)}"
            )
        row += el.count
        if el.name not in ("vertex", "face"):
            continue
        out[el.name] = _ply_ascii_element(path, rows, el)
    return out


def _ply_ascii_element(path, rows, el: _Element) -> dict:
    import pandas as pd

    nscal = len(el.props)
    has_list = any(p.count_dtype for p in el.props)
    if not has_list:
        block = "\n".join(r for _, r in rows)
        try:
            arr = pd.read_csv(io.StringIO(block), sep=r"\s+", header=None, names=list(range(nscal)),
                              dtype=np.float64, engine="c", keep_default_na=False,
                              na_values=["nan", "NaN"], quoting=3).to_numpy()
            ok = arr.shape == (el.count, nscal) and not np.isnan(arr).any()
        except (ValueError, pd.errors.ParserError):
            ok = False
        if ok:
            return {p.name: arr[:, n] for n, p in enumerate(el.props)}
    elif len(el.props) == 1:  # the usual face element: one list property only
        flat = _ply_ascii_lists(rows)
        if flat is not None:
            return {el.props[0].name: flat}
    # general (and diagnostic) path: token by token per row
    scal = {p.name: np.empty(el.count) for p in el.props if p.count_dtype is None}
    lst = {p.name: ([], []) for p in el.props if p.count_dtype is not None}
    for r, (ln, line) in enumerate(rows):
        toks = line.split()
        t = 0
        try:
            for p in el.props:
                if p.count_dtype is None:
                    scal[p.name][r] = float(toks[t])
                    t += 1
                else:
                    k = int(toks[t])
                    items = [int(x) for x in toks[t + 1 : t + 1 + k]]
                    if len(items) != k or k < 0:
                        raise IndexError
                    lst[p.name][0].append(k)
                    lst[p.name][1].extend(items)
                    t += 1 + k
        except (IndexError, ValueError):
            raise InputDataError(f"{path}: line {ln}: malformed {el.name} row {line.strip()[:80]!r}") from None
        if t != len(toks):
            raise InputDataError(f"{path}: line {ln}: {len(toks) - t} extra value(s) on a {el.name} row")
    vals = dict(scal)
    for n, (ks, items) in lst.items():
        vals[n] = (np.asarray(ks, dtype=np.int64), np.asarray(items, dtype=np.int64))
    return vals


def _ply_ascii_lists(rows):
    """Vectorised parse of ASCII rows ``n i1 .. in``; None when anything looks off."""
    import pandas as pd

    from vlsforest.io._text import token_counts

    block = "\n".join(r for _, r in rows).encode("ascii", errors="replace")
    counts = token_counts(block)[: len(rows)]
    if len(counts) != len(rows) or counts.min() < 1:
        return None
    width = int(counts.max())
    try:
        arr = pd.read_csv(io.BytesIO(block), sep=r"\s+", header=None, names=list(range(width)),
                          dtype=np.float64, engine="c", keep_default_na=False, na_values=[""],
                          skip_blank_lines=False, quoting=3).to_numpy()
    except (ValueError, pd.errors.ParserError):
        return None
    if arr.shape != (len(rows), width) or not np.array_equal(arr[:, 0], counts - 1):
        return None
    vals = arr[:, 1:][np.arange(width - 1)[None, :] < (counts - 1)[:, None]]
    if not (np.all(np.isfinite(vals)) and np.all(vals == np.round(vals))):
        return None
    return counts - 1, vals.astype(np.int64)


# ====================================================================== writing
def write_mesh(path, mesh: TriangleMesh) -> None:
    """Write a mesh as ``.obj`` (text, exact shortest-repr floats) or ``.ply`` (binary little endian,
    float64 vertices, ``uchar``/``int`` face lists). Same mesh, same bytes.

    Parameters
    ----------
    path : str or Path
        Output file; the extension picks the format.
    mesh : TriangleMesh
        The mesh.

    Raises
    ------
    InputDataError
        For an extension other than ``.obj`` or ``.ply``.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in (".obj", ".ply"):
        raise InputDataError(f"{path}: unknown mesh format {path.suffix!r} (use .obj or .ply)")
    mesh = TriangleMesh(mesh.vertices, mesh.faces)  # validate
    if not np.all(np.isfinite(mesh.vertices)):
        raise InputDataError(f"{path}: cannot write a mesh with NaN or infinite vertex coordinates")
    if ext == ".obj":
        from vlsforest.io._text import column_text, join_rows

        nv, nf = mesh.n_vertices, mesh.n_faces
        head = f"# vlsforest triangle mesh: {nv} vertices, {nf} faces\n".encode()
        vcols = [np.full(nv, b"v", dtype="S1")] + [_float_text(mesh.vertices[:, n]) for n in range(3)]
        fcols = [np.full(nf, b"f", dtype="S1")] + [
            column_text(mesh.faces[:, n].astype(np.int64) + 1) for n in range(3)
        ]
        body = (join_rows(vcols) if nv else b"") + (join_rows(fcols) if nf else b"")
        write_bytes(path, head + body)
    else:
        head = (
            "ply\nformat binary_little_endian 1.0\ncomment vlsforest triangle mesh\n"
            f"element vertex {mesh.n_vertices}\nproperty double x\nproperty double y\nproperty double z\n"
            f"element face {mesh.n_faces}\nproperty list uchar int vertex_indices\nend_header\n"
        ).encode("ascii")
        frec = np.zeros(mesh.n_faces, dtype=[("n", "u1"), ("idx", "<i4", (3,))])
        frec["n"] = 3
        frec["idx"] = mesh.faces
        write_bytes(path, head + mesh.vertices.astype("<f8").tobytes() + frec.tobytes())


def _float_text(a: np.ndarray) -> np.ndarray:
    """Shortest round-trip text of float64 values (never integers-without-dot, for OBJ readers)."""
    out = np.asarray(a, dtype=np.float64).astype("S32")
    if len(out):
        out = out.astype(f"S{int(np.strings.str_len(out).max())}")
    return out


__all__ = ["TriangleMesh", "read_mesh", "write_mesh"]
