"""Tests of the AMAPVox ``.vox`` and triangle-mesh (OBJ/PLY) readers and writers, and of the CSV table reader."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from vlsforest.errors import InputDataError
from vlsforest.io.mesh import TriangleMesh, read_mesh, write_mesh
from vlsforest.io.vox import STANDARD_COLUMNS, VoxFile, make_vox, read_vox, write_vox

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
REAL_VOX = REAL / "F_BR08_08_crown_250.vox"
REAL_OBJ = REAL / "F_BR08_08_stem_Poisson.obj"

COLUMN_LINE = "i j k " + " ".join(STANDARD_COLUMNS)


# ==========================================================================================
# .vox
# ==========================================================================================
def _random_vox(n=500, seed=3):
    rng = np.random.default_rng(seed)
    split = np.array([17, 11, 23])
    lin = rng.choice(np.prod(split), size=n, replace=False)
    ijk = np.stack(np.unravel_index(lin, split), axis=1)
    pad = rng.random(n) * 5.0
    pad[rng.random(n) < 0.1] = np.nan
    ang = rng.uniform(0, 180, n)
    ang[:3] = [np.inf, -np.inf, -0.0]
    extreme = np.array([5e-324, 1.7976931348623157e308, 0.1, 1 / 3, -2.5e-17])
    extra = np.resize(extreme, n)
    return make_vox(
        ijk,
        res=0.1,
        min_corner=[-3.05, 12.15, 240.0],
        columns={"PadBVTotal": pad, "angleMean": ang, "nbEchos": rng.integers(0, 50, n), "myextra": extra},
        max_pad=5.0,
        header={"build-version": "1.4.3", "lad_type": "Planophile"},
        split=split,
    )


def test_vox_roundtrip_exact_and_byte_identical(tmp_path):
    v = _random_vox()
    a, b = tmp_path / "a.vox", tmp_path / "b.vox"
    write_vox(a, v)
    r = read_vox(a)
    assert r == v
    # arrays equal including NaN positions, signed zero and infinities
    for c in v.columns:
        x, y = v.data[c], r.data[c]
        assert x.dtype == y.dtype
        if x.dtype.kind == "f":
            assert np.array_equal(np.isnan(x), np.isnan(y))
            assert np.array_equal(np.signbit(x), np.signbit(y))
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f")
    assert r.data["i"].dtype == np.int32 and r.data["PadBVTotal"].dtype == np.float64
    write_vox(b, r)
    assert a.read_bytes() == b.read_bytes()
    # the AMAPVox layout: header lines in order, extra items on the #res: line, max_pad readable
    lines = a.read_text().splitlines()
    assert lines[0] == "VOXEL SPACE"
    assert lines[1].startswith("#min_corner: ") and lines[2].startswith("#max_corner: ")
    assert lines[3] == "#split: 17 11 23"
    assert lines[4] == "#res: 0.1 #build-version: 1.4.3 #lad_type: Planophile #max_pad: 5.0"
    assert lines[5] == COLUMN_LINE + " myextra"
    assert len(lines) == 6 + v.n_voxels
    assert r.max_pad == 5.0
    assert list(r.header) == ["build-version", "lad_type", "max_pad"]
    assert "NaN" in a.read_text() and "-Infinity" in a.read_text()


def test_vox_centres_and_accessors():
    ijk = np.array([[0, 0, 0], [3, 1, 7], [2, 5, 1]])
    v = make_vox(ijk, res=0.25, min_corner=[9.875, -18.125, 247.875])
    # cell (3, 1, 7): lower corner min + ijk*res, centre half a cell further
    assert np.allclose(v.centres()[1], [9.875 + 3.5 * 0.25, -18.125 + 1.5 * 0.25, 247.875 + 7.5 * 0.25])
    assert v.n_voxels == 3
    assert np.array_equal(v.ijk, ijk) and v.ijk.dtype == np.int32
    assert np.array_equal(v.split, [4, 6, 8])
    assert np.allclose(v.max_corner, v.min_corner + v.split * 0.25)
    assert v.columns == ["i", "j", "k", *STANDARD_COLUMNS]
    for c in STANDARD_COLUMNS:
        assert np.array_equal(v.column(c), np.zeros(3))
    assert v.max_pad is None
    with pytest.raises(InputDataError, match="nope"):
        v.column("nope")
    with pytest.raises(InputDataError):
        make_vox(ijk, 0.25, [0, 0, 0], columns={"i": [1, 2, 3]})
    with pytest.raises(InputDataError):
        make_vox([[0, 0, -1]], 0.25, [0, 0, 0])


def test_voxfile_validation():
    base = dict(min_corner=[0, 0, 0], max_corner=[2, 2, 2], split=[2, 2, 2], res=1.0)
    ok = VoxFile(**base, columns=["i", "j", "k", "a"], data={"i": [0], "j": [1], "k": [1], "a": [0.5]})
    assert ok.n_voxels == 1 and ok.data["a"].dtype == np.float64 and ok.data["i"].dtype == np.int32
    with pytest.raises(InputDataError, match="i j k"):
        VoxFile(**base, columns=["a", "i", "j"], data={"a": [0], "i": [0], "j": [0]})
    with pytest.raises(InputDataError, match="'a' has 2 values"):
        VoxFile(**base, columns=["i", "j", "k", "a"], data={"i": [0], "j": [0], "k": [0], "a": [1, 2]})
    with pytest.raises(InputDataError, match="header item 'res'"):
        VoxFile(**base, header={"res": "2"}, columns=["i", "j", "k"], data={"i": [0], "j": [0], "k": [0]})
    with pytest.raises(InputDataError, match="#res"):
        VoxFile(**{**base, "res": 0.0}, columns=["i", "j", "k"], data={"i": [0], "j": [0], "k": [0]})
    with pytest.raises(InputDataError, match="whole numbers"):
        VoxFile(**base, columns=["i", "j", "k"], data={"i": [0.5], "j": [0], "k": [0]})


def test_vox_reads_amapvox_style_header_and_odd_spacing(tmp_path):
    text = (
        "VOXEL SPACE\r\n"
        "#min_corner:1.5 -2 3\r\n"
        "#max_corner: 4.5 1 6\r\n"
        "#split:3 3 3\r\n"
        "#res:1.0 #nsubvoxel:5 #nbScanners:3 #max_pad:5.0 #lad_type:Spherical #build-version:1.4.3\r\n"
        f"{COLUMN_LINE}\r\n"
        "0 0 0 NaN 1 2 3 4 5 6 7 8 9 10 11 12\r\n"
        "  2\t1  2 nan Infinity -Infinity 0.5 1e-3 -0 6 7 8 9 10 11 12   \r\n"
        "\r\n"
        "1 1 1 2.5 0 0 0 0 0 0 0 0 0 0 0 0\r\n"
        "\r\n"
    )
    p = tmp_path / "odd.vox"
    p.write_bytes(text.encode())
    v = read_vox(p)
    assert v.n_voxels == 3
    assert np.array_equal(v.min_corner, [1.5, -2.0, 3.0]) and v.res == 1.0
    assert list(v.header.items()) == [
        ("nsubvoxel", "5"),
        ("nbScanners", "3"),
        ("max_pad", "5.0"),
        ("lad_type", "Spherical"),
        ("build-version", "1.4.3"),
    ]
    assert v.max_pad == 5.0
    pad = v.column("PadBVTotal")
    assert np.isnan(pad[0]) and np.isnan(pad[1]) and pad[2] == 2.5
    assert v.column("angleMean")[1] == np.inf and v.column("bsEntering")[1] == -np.inf
    assert v.column("bsPotential")[1] == 1e-3
    assert np.array_equal(v.ijk, [[0, 0, 0], [2, 1, 2], [1, 1, 1]])
    assert np.allclose(v.centres()[1], [1.5 + 2.5, -2 + 1.5, 3 + 2.5])
    # a written copy reads back to the same content
    write_vox(tmp_path / "copy.vox", v)
    assert read_vox(tmp_path / "copy.vox") == v


@pytest.mark.realdata
def test_vox_real_bretten_crown(tmp_path):
    if not REAL_VOX.exists():
        pytest.skip("real data folder absent")
    v = read_vox(REAL_VOX)
    assert v.n_voxels == 6185
    assert np.array_equal(v.min_corner, [9.875, -18.125, 247.875])
    assert np.array_equal(v.max_corner, [16.0, -12.0, 270.0])  # as written, although inconsistent
    assert np.array_equal(v.split, [24, 24, 87])
    assert v.res == 0.25
    assert v.columns == ["i", "j", "k", *STANDARD_COLUMNS]
    assert np.all(v.column("PadBVTotal") == 0)
    assert v.max_pad is None
    ijk = v.ijk
    assert np.all(ijk >= 0) and np.all(ijk < v.split)
    # centres lie on multiples of the 0.25 m cell size (min_corner = multiple - res/2), inside the box
    c = v.centres()
    assert np.array_equal(c / 0.25, np.round(c / 0.25))
    assert np.all(c > v.min_corner) and np.all(c < v.min_corner + v.split * v.res)
    write_vox(tmp_path / "r.vox", v)
    assert read_vox(tmp_path / "r.vox") == v


def _vox_text(header=None, column_line=COLUMN_LINE, rows=("0 0 0" + " 0" * 13,), first="VOXEL SPACE"):
    if header is None:
        header = ["#min_corner: 0 0 0", "#max_corner: 2 2 2", "#split: 2 2 2", "#res: 1 #max_pad: 5"]
    lines = [first, *header]
    if column_line is not None:
        lines.append(column_line)
    return "\n".join([*lines, *rows]) + "\n"


_ZERO13 = " 0" * 13
_VOX_ERRORS = {
    "empty": ("", "empty"),
    "blank": ("\n \n", "empty"),
    "not_vox": ("NOT A VOX\n#res: 1\n", "VOXEL SPACE"),
    "no_min_corner": (_vox_text(header=["#split: 2 2 2", "#res: 1"]), "min_corner"),
    "no_res": (_vox_text(header=["#min_corner: 0 0 0", "#split: 2 2 2"]), "#res"),
    "no_split": (_vox_text(header=["#min_corner: 0 0 0", "#res: 1"]), "#split"),
    "bad_min_corner": (_vox_text(header=["#min_corner: 0 x 0", "#split: 2 2 2", "#res: 1"]), "line 2"),
    "no_column_line": (_vox_text(column_line=None), "line 6"),
    "header_only": (_vox_text(column_line=None, rows=()), "column-name"),
    "i_outside": (_vox_text(rows=("0 0 0" + _ZERO13, "2 0 0" + _ZERO13)), "line 8"),
    "k_negative": (_vox_text(rows=("0 0 -1" + _ZERO13,)), "line 7"),
    "i_fraction": (_vox_text(rows=("0.5 0 0" + _ZERO13,)), "line 7"),
    "too_few": (_vox_text(rows=("0 0 0" + _ZERO13, "1 1 1" + " 0" * 12)), "line 8"),
    "too_many": (_vox_text(rows=("0 0 0" + _ZERO13 + " 7",)), "line 7"),
    "non_numeric": (_vox_text(rows=("0 0 0" + _ZERO13, "1 0 0 0 abc" + " 0" * 11)), "line 8.*abc.*angleMean"),
    "duplicate": (_vox_text(rows=("0 0 0" + _ZERO13, "1 1 1" + _ZERO13, "0 0 0" + _ZERO13)), "line 9.*twice"),
}


@pytest.mark.parametrize("case", sorted(_VOX_ERRORS))
def test_vox_errors_name_the_file(tmp_path, case):
    text, pattern = _VOX_ERRORS[case]
    p = tmp_path / f"bad_{case}.vox"
    p.write_text(text)
    with pytest.raises(InputDataError, match=pattern) as e:
        read_vox(p)
    assert f"bad_{case}.vox" in str(e.value)


def test_vox_missing_file_and_unwritable_content(tmp_path):
    with pytest.raises(InputDataError, match="nothere.vox"):
        read_vox(tmp_path / "nothere.vox")
    v = make_vox([[0, 0, 0], [1, 1, 1]], 1.0, [0, 0, 0])
    v.data["i"][1] = 5  # outside split (2, 2, 2)
    with pytest.raises(InputDataError, match="out.vox"):
        write_vox(tmp_path / "out.vox", v)
    v.data["i"][1] = 0
    v.data["j"][1] = 0
    v.data["k"][1] = 0  # now a duplicate of (0, 0, 0)
    with pytest.raises(InputDataError, match="twice"):
        write_vox(tmp_path / "out.vox", v)


def test_vox_large_roundtrip(tmp_path):
    """200 000 voxels through the vectorised writer and reader, exact."""
    rng = np.random.default_rng(11)
    split = np.array([100, 100, 100])
    lin = rng.choice(np.prod(split), size=200_000, replace=False)
    ijk = np.stack(np.unravel_index(lin, split), axis=1)
    v = make_vox(ijk, 0.02, [0.01, -5.0, 100.0], columns={"PadBVTotal": rng.random(len(ijk))}, split=split)
    write_vox(tmp_path / "big.vox", v)
    assert read_vox(tmp_path / "big.vox") == v


# ==========================================================================================
# meshes
# ==========================================================================================
CUBE_V = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=float
)
# outward (counter-clockwise seen from outside) quads, 0-based
CUBE_Q = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def _check_unit_cube(m: TriangleMesh, offset=(0.0, 0.0, 0.0)):
    assert m.n_faces == 12 and m.n_vertices == 8
    assert m.faces.dtype == np.int32 and m.vertices.dtype == np.float64
    assert m.area() == pytest.approx(6.0, abs=1e-12)
    assert np.allclose(m.face_areas(), 0.5)
    n = m.face_normals()
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    centroid = m.vertices[m.faces].mean(axis=1)
    outward = centroid - (np.asarray(offset) + 0.5)
    assert np.all(np.einsum("ij,ij->i", n, outward) > 0.49)  # each normal is the outward axis
    # divergence theorem: the signed volume of a closed outward mesh is its volume
    v = m.vertices[m.faces]
    assert np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6 == pytest.approx(1.0)
    assert np.allclose(m.bounds(), [np.add(offset, 0.0), np.add(offset, 1.0)])


def _cube_obj_text():
    lines = ["# a unit cube", "mtllib cube.mtl", "o cube", "g box", "s off", "usemtl wood"]
    lines += [f"v {x:g} {y:g} {z:g}" for x, y, z in CUBE_V]
    lines += ["vt 0 0", "vt 1 0", "vn 0 0 1"]
    styles = [lambda a: f"{a}", lambda a: f"{a}/1", lambda a: f"{a}/2/1", lambda a: f"{a}//1"]
    for n, q in enumerate(CUBE_Q):
        if n == 5:  # negative indices relative to the 8 vertices read so far
            lines.append("f " + " ".join(str(a - 8) for a in q))
        else:
            lines.append("f " + " ".join(styles[(n + c) % 4](a + 1) for c, a in enumerate(q)))
    return "\n".join(lines) + "\n"


def test_obj_cube_quads_tokens_and_negative_indices(tmp_path):
    p = tmp_path / "cube.obj"
    p.write_text(_cube_obj_text())
    m = read_mesh(p)
    _check_unit_cube(m)
    # fan triangulation in file order: quad (0,3,2,1) -> (0,3,2), (0,2,1)
    assert m.faces[:2].tolist() == [[0, 3, 2], [0, 2, 1]]
    # CRLF line endings and leading blanks give the same mesh
    p2 = tmp_path / "cube_crlf.obj"
    p2.write_bytes(_cube_obj_text().replace("\nv ", "\n  v ").replace("\n", "\r\n").encode())
    m2 = read_mesh(p2)
    assert np.array_equal(m2.vertices, m.vertices) and np.array_equal(m2.faces, m.faces)


def _ply_bytes(fmt: str, polys, verts=CUBE_V, extra_face_prop=True, index_type="int", count_type="uchar"):
    """A PLY with extra vertex properties, an extra element and an extra face property to skip."""
    head = [
        "ply",
        f"format {fmt} 1.0",
        "comment test file",
        "obj_info nothing",
        f"element vertex {len(verts)}",
        "property float x",
        "property double y",
        "property uchar red",
        "property float z",
        "property short quality",
        "element material 2",
        "property list uchar float coeffs",
        "property int id",
        f"element face {len(polys)}",
        f"property list {count_type} {index_type} vertex_indices",
    ]
    if extra_face_prop:
        head.append("property uchar flags")
    head.append("end_header")
    out = ("\n".join(head) + "\n").encode()
    if fmt == "ascii":
        rows = [f"{x:g} {y:g} 200 {z:g} -3" for x, y, z in verts]
        rows += ["2 0.5 0.25 7", "0 8"]
        rows += [" ".join([str(len(q)), *map(str, q)] + (["1"] if extra_face_prop else [])) for q in polys]
        return out + ("\n".join(rows) + "\n").encode()
    e = "<" if fmt == "binary_little_endian" else ">"
    ct = {"uchar": "B", "int": "i", "uint": "I"}[count_type]
    it = {"int": "i", "uint": "I", "ushort": "H"}[index_type]
    for x, y, z in verts:
        out += struct.pack(e + "fdBfh", x, y, 200, z, -3)
    out += struct.pack(e + "B2fi", 2, 0.5, 0.25, 7) + struct.pack(e + "Bi", 0, 8)
    for q in polys:
        out += struct.pack(e + ct + it * len(q), len(q), *q)
        if extra_face_prop:
            out += struct.pack(e + "B", 1)
    return out


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_cube_all_encodings(tmp_path, fmt):
    p = tmp_path / f"cube_{fmt}.ply"
    p.write_bytes(_ply_bytes(fmt, CUBE_Q))
    m = read_mesh(p)
    _check_unit_cube(m)
    ref = read_mesh(_write_text(tmp_path / "ref.obj", _cube_obj_text()))
    assert np.array_equal(m.vertices, ref.vertices) and np.array_equal(m.faces, ref.faces)
    # other integer types for counts and indices
    p2 = tmp_path / f"cube2_{fmt}.ply"
    p2.write_bytes(_ply_bytes(fmt, CUBE_Q, extra_face_prop=False, index_type="uint", count_type="int"))
    m2 = read_mesh(p2)
    assert np.array_equal(m2.faces, ref.faces)


def _write_text(p, text):
    p.write_text(text)
    return p


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_mixed_polygons_fan_order(tmp_path, fmt):
    verts = np.array([[np.cos(a), np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 6)[:5]] + [[0, 0, 1]])
    polys = [[0, 1, 2, 3, 4], [0, 1, 5], [1, 2, 5, 5]]
    expected = [[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 1, 5], [1, 2, 5], [1, 5, 5]]
    p = tmp_path / f"mixed_{fmt}.ply"
    p.write_bytes(_ply_bytes(fmt, polys, verts=verts))
    m = read_mesh(p)
    assert m.faces.tolist() == expected
    assert np.allclose(m.vertices, verts.astype(np.float32))  # x and z are stored as float32
    # regular pentagon of circumradius 1: area 5/2 sin(72 deg); the degenerate triangle has none
    assert m.face_areas()[:3].sum() == pytest.approx(2.5 * np.sin(np.radians(72)), rel=1e-6)
    assert m.face_areas()[5] == 0.0 and np.array_equal(m.face_normals()[5], [0, 0, 0])
    obj = tmp_path / "mixed.obj"
    obj.write_text(
        "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in verts.tolist())
        + "".join("f " + " ".join(str(a + 1) for a in q) + "\n" for q in polys)
    )
    assert read_mesh(obj).faces.tolist() == expected


@pytest.mark.parametrize("ext", [".obj", ".ply"])
def test_mesh_write_roundtrip_exact_and_deterministic(tmp_path, ext):
    rng = np.random.default_rng(5)
    v = rng.normal(size=(2000, 3)) * 10.0 ** rng.integers(-3, 4, size=(2000, 1)) + [12.1, -14.7, 241.6]
    f = rng.integers(0, 2000, size=(5000, 3))
    m = TriangleMesh(v, f)
    a, b = tmp_path / f"a{ext}", tmp_path / f"b{ext}"
    write_mesh(a, m)
    r = read_mesh(a)
    assert np.array_equal(r.vertices, m.vertices) and np.array_equal(r.faces, m.faces)
    write_mesh(b, r)
    assert a.read_bytes() == b.read_bytes()
    # translate keeps shape and area, moves the bounds
    t = m.translate([1.0, -2.0, 3.0])
    assert np.allclose(t.bounds(), m.bounds() + [1.0, -2.0, 3.0])
    assert t.area() == pytest.approx(m.area(), rel=1e-9)
    assert np.array_equal(m.vertices, v)  # the original is untouched


def test_cube_write_read_each_format(tmp_path):
    quads = np.array(CUBE_Q)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    m = TriangleMesh(CUBE_V + 10.0, tris)
    _check_unit_cube(m, offset=(10.0, 10.0, 10.0))
    for ext in (".obj", ".ply"):
        write_mesh(tmp_path / f"c{ext}", m)
        _check_unit_cube(read_mesh(tmp_path / f"c{ext}"), offset=(10.0, 10.0, 10.0))


def test_obj_large_vectorised(tmp_path):
    """150 000 lines with mixed a/b/c tokens and a negative index per face, exact."""
    rng = np.random.default_rng(8)
    nv, nf = 50_000, 100_000
    v = np.round(rng.random((nv, 3)) * 100, 6)
    f = rng.integers(0, nv, (nf, 3))
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in v.tolist()]
    lines += [f"f {a + 1}/{a + 1} {b + 1}//{b + 1} {c - nv}" for a, b, c in f]
    p = tmp_path / "big.obj"
    p.write_text("\n".join(lines))  # no final newline
    m = read_mesh(p)
    assert np.array_equal(m.vertices, v) and np.array_equal(m.faces, f)


@pytest.mark.realdata
def test_real_poisson_stem_obj():
    if not REAL_OBJ.exists():
        pytest.skip("real data folder absent")
    m = read_mesh(REAL_OBJ)
    assert m.n_vertices == 3280 and m.n_faces == 6556
    zmin = m.bounds()[0, 2]
    assert 241.5 <= zmin <= 241.8
    # first vertex and first face as written in the file ('f 6//6 11//11 3//3', 1-based)
    first_v = next(ln for ln in REAL_OBJ.read_text().splitlines() if ln.startswith("v "))
    assert np.array_equal(m.vertices[0], [float(t) for t in first_v.split()[1:4]])
    assert m.faces[0].tolist() == [5, 10, 2]
    # closed and untrimmed: every edge in exactly two triangles, Euler characteristic 2
    e = np.sort(np.concatenate([m.faces[:, [0, 1]], m.faces[:, [1, 2]], m.faces[:, [2, 0]]]), axis=1)
    _, cnt = np.unique(e, axis=0, return_counts=True)
    assert np.all(cnt == 2)
    assert m.n_vertices - len(cnt) + m.n_faces == 2
    v = m.vertices[m.faces] - m.vertices.mean(axis=0)
    assert np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6 > 0  # outward


_CUBE_V_TXT = "".join(f"v {x:g} {y:g} {z:g}\n" for x, y, z in CUBE_V)
_MESH_ERRORS = {
    "no_faces.obj": (_CUBE_V_TXT, "no faces"),
    "only_comments.obj": ("# nothing\nvn 0 0 1\n", "no faces"),
    "out_of_range.obj": (_CUBE_V_TXT + "f 1 2 3\nf 1 2 9\n", "line 10.*out of range"),
    "negative_too_far.obj": (_CUBE_V_TXT + "f -1 -2 -9\n", "line 9.*out of range"),
    "zero_index.obj": (_CUBE_V_TXT + "f 0 1 2\n", "line 9"),
    "nan_vertex.obj": (_CUBE_V_TXT + "v nan 0 0\nf 1 2 3\n", "line 9.*NaN"),
    "short_vertex.obj": ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", "line 2.*x y z"),
    "bad_number.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 zz\nf 1 2 3\n", "line 3.*zz"),
    "bad_face_token.obj": (_CUBE_V_TXT + "f 1 2 3\nf 1 x 3\n", "line 10.*'x'"),
    "slash_first.obj": (_CUBE_V_TXT + "f 1 2 /3\n", "line 9"),
    "two_vertex_face.obj": (_CUBE_V_TXT + "f 1 2\n", "line 9.*at least 3"),
    "empty.ply": ("", "empty"),
    "not_ply.ply": ("hello\nend_header\n", "not a PLY"),
    "no_face.ply": (
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n0 0 0\n1 0 0\n0 1 0\n",
        "no faces",
    ),
    "no_x.ply": (
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0\n3 0 0 0\n",
        "'x'",
    ),
    "bad_row.ply": (
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 q\n3 0 1 2\n",
        "line 12",
    ),
    "ply_index_out_of_range.ply": (
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n",
        "out of range",
    ),
    "nan.ply": (
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 nan 0\n0 1 0\n3 0 1 2\n",
        "NaN",
    ),
    "cube.stl": ("solid x\n", "unknown mesh format"),
}


@pytest.mark.parametrize("name", sorted(_MESH_ERRORS))
def test_mesh_errors_name_the_file(tmp_path, name):
    text, pattern = _MESH_ERRORS[name]
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(InputDataError, match=pattern) as e:
        read_mesh(p)
    assert name in str(e.value)


def test_mesh_binary_truncated_and_missing(tmp_path):
    data = _ply_bytes("binary_little_endian", [[0, 1, 2], [0, 2, 3, 4]], extra_face_prop=False)
    p = tmp_path / "trunc.ply"
    p.write_bytes(data[:-3])
    with pytest.raises(InputDataError, match="trunc.ply.*truncated"):
        read_mesh(p)
    with pytest.raises(InputDataError, match="missing.obj"):
        read_mesh(tmp_path / "missing.obj")
    with pytest.raises(InputDataError, match="out.stl"):
        write_mesh(tmp_path / "out.stl", TriangleMesh(CUBE_V, [[0, 1, 2]]))
    with pytest.raises(InputDataError, match="out of range"):
        TriangleMesh(CUBE_V, [[0, 1, 8]])


def test_las_flag_fields_round_trip_as_standard_fields(tmp_path):
    """Point-format-6 flag bits (synthetic … edge of flight line, scanner channel) read from one
    file are written back into the flag byte, not duplicated as extra dimensions."""
    import laspy

    from vlsforest.io.las import PointCloud, read_las, write_las

    n = 12
    attrs = {"synthetic": np.arange(n) % 2, "key_point": (np.arange(n) % 3 == 1).astype(np.uint8),
             "withheld": np.zeros(n, np.uint8), "overlap": (np.arange(n) > 6).astype(np.uint8),
             "scanner_channel": np.arange(n) % 4, "scan_direction_flag": np.ones(n, np.uint8),
             "edge_of_flight_line": (np.arange(n) % 5 == 0).astype(np.uint8)}
    write_las(tmp_path / "a.las", PointCloud(np.random.default_rng(0).random((n, 3)), attrs))
    back = read_las(tmp_path / "a.las")
    for k, v in attrs.items():
        assert np.array_equal(back.attrs[k], v), k
    assert list(laspy.read(tmp_path / "a.las").point_format.extra_dimension_names) == []
    write_las(tmp_path / "b.las", back)
    assert list(laspy.read(tmp_path / "b.las").point_format.extra_dimension_names) == []


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("spill_bytes", [None, 1, 200_000])
def test_las_pieces_write_the_bytes_of_the_joined_cloud(tmp_path, suffix, spill_bytes):
    """A file gathered in pieces (one of them empty, the smallest coordinates in the last) holds
    the bytes write_las writes for the pieces joined, whether the earlier pieces stay in memory,
    all go to the temporary file (spill_bytes 1) or some do (200 kB: the first four of the
    seven pieces); a piece with other attributes is refused, nothing is written before write(),
    and nothing but the file is left in its folder."""
    from vlsforest.io.las import LasPieces, PointCloud, write_las

    rng = np.random.default_rng(3)
    n = 5000
    xyz = rng.normal(size=(n, 3)) * 40 + [512.3, -20.7, 300.0]
    xyz[-1] = [400.0, -120.5, 250.2]  # the offsets come from the last piece
    attrs = {"intensity": rng.integers(0, 65535, n).astype(np.uint16),
             "return_number": rng.integers(1, 4, n).astype(np.uint8), "number_of_returns": np.full(n, 3, np.uint8),
             "gps_time": rng.random(n) * 100, "scan_angle": rng.normal(size=n) * 20,
             "object_id": rng.integers(0, 9, n).astype(np.int32), "amplitude": rng.random(n).astype(np.float32)}
    write_las(tmp_path / f"whole{suffix}", PointCloud(xyz, attrs))
    pieces = LasPieces(tmp_path / f"pieces{suffix}", **({} if spill_bytes is None else {"spill_bytes": spill_bytes}))
    for a, b in ((0, 1700), (1700, 1700), (1700, 2300), (2300, 2301), (2301, 3999), (3999, 4000), (4000, n)):
        pieces.add(PointCloud(xyz[a:b], {k: v[a:b] for k, v in attrs.items()}))
    assert pieces.n_points == n and not (tmp_path / f"pieces{suffix}").exists()
    with pytest.raises(ValueError, match="attributes"):
        pieces.add(PointCloud(xyz[:2], {k: v[:2] for k, v in attrs.items() if k != "amplitude"}))
    pieces.write()
    assert (tmp_path / f"pieces{suffix}").read_bytes() == (tmp_path / f"whole{suffix}").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([f"pieces{suffix}", f"whole{suffix}"])
    with pytest.raises(ValueError, match="no piece"):
        LasPieces(tmp_path / f"none{suffix}").write()


# ==========================================================================================
# CSV tables
# ==========================================================================================
def test_read_csv_table_reads_the_columns(tmp_path):
    from vlsforest.io.csvfile import read_csv_table

    path = tmp_path / "t.csv"
    path.write_text("tree_id,x\n7,1.5\n8,2.5\n")
    df = read_csv_table(path, "tree table", ("tree_id", "x"))
    assert list(df.columns) == ["tree_id", "x"] and df["x"].tolist() == [1.5, 2.5]


@pytest.mark.parametrize("content, needle", [
    (None, "t.csv: no such tree table"),
    (b"", "t.csv: not a readable CSV (No columns to parse from file)"),
    (b"tree_id,x\n1,2\n1,2,3,4\n", "t.csv: not a readable CSV (Error tokenizing data."),
    (b"tree_id,y\n1,2\n", "t.csv: tree table lacks column(s) ['x']"),
])
def test_read_csv_table_errors_are_one_line_naming_the_file(tmp_path, content, needle):
    from vlsforest.io.csvfile import read_csv_table

    path = tmp_path / "t.csv"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputDataError) as err:
        read_csv_table(path, "tree table", ("tree_id", "x"))
    msg = str(err.value)
    assert msg.startswith(str(path)) and needle in msg and "\n" not in msg


def test_read_height_table_types_ids_and_heights(tmp_path):
    from vlsforest.io.csvfile import read_height_table

    path = tmp_path / "g.csv"
    path.write_text("target_id,group,z\n301,conifer,299.5\n302.0,broadleaf,280\n")
    df = read_height_table(path, "targets table", ids=("target_id",), columns=("group",))
    assert df["target_id"].tolist() == [301, 302] and df["target_id"].dtype == np.int64
    assert df["z"].tolist() == [299.5, 280.0] and df["group"].tolist() == ["conifer", "broadleaf"]


@pytest.mark.parametrize("content, needle", [
    ("target_id\n301\n", "g.csv: ground table lacks column(s) ['z']"),
    ("target_id,z\n301,nan\n", "column 'z' that are not finite numbers"),
    ("target_id,z\n301,high\n", "column 'z' that are not finite numbers"),
    ("target_id,z\n301,inf\n", "column 'z' that are not finite numbers"),
    ("target_id,z\n301.5,1\n", "ids in column 'target_id' that are not integers"),
    ("target_id,z\nP1,1\n", "ids in column 'target_id' that are not integers"),
])
def test_read_height_table_errors_name_the_column(tmp_path, content, needle):
    from vlsforest.io.csvfile import read_height_table

    path = tmp_path / "g.csv"
    path.write_text(content)
    with pytest.raises(InputDataError) as err:
        read_height_table(path, "ground table", ids=("target_id",))
    msg = str(err.value)
    assert msg.startswith(str(path)) and needle in msg and "\n" not in msg
