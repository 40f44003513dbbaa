"""An embedded, seeded demo scene: one spruce-like tree (voxel crown + stem mesh) on a ground plane.

A small self-contained scene for trying the simulator (``vlsforest demo``), and a fixture of
tests and benchmarks. Everything is generated from the seed; nothing is read from disk.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from vlsforest.errors import ConfigError
from vlsforest.io.atomic import atomic_path, write_text
from vlsforest.io.mesh import TriangleMesh, write_mesh


def stem_mesh(base, height: float, dbh: float, n_seg: int = 24, n_rings: int = 30) -> TriangleMesh:
    """A closed, linearly tapered stem (frustum) from ``base`` up to ``height``."""
    base = np.asarray(base, dtype=np.float64)
    z = np.linspace(0.0, height, n_rings)
    r = 0.5 * dbh * np.clip(1.0 - z / height, 0.02, None) * 1.15
    a = np.arange(n_seg) * 2 * np.pi / n_seg
    ring = np.stack([np.outer(r, np.cos(a)), np.outer(r, np.sin(a)), np.repeat(z[:, None], n_seg, 1)], axis=-1)
    v = ring.reshape(-1, 3) + base
    faces = []
    for i in range(n_rings - 1):
        for j in range(n_seg):
            p, q = i * n_seg + j, i * n_seg + (j + 1) % n_seg
            faces += [[p, q, q + n_seg], [p, q + n_seg, p + n_seg]]
    bottom, top = len(v), len(v) + 1
    v = np.vstack([v, base, base + [0, 0, height]])
    for j in range(n_seg):
        faces.append([bottom, (j + 1) % n_seg, j])
        k = (n_rings - 1) * n_seg
        faces.append([top, k + j, k + (j + 1) % n_seg])
    return TriangleMesh(v, np.asarray(faces, dtype=np.int32))


def conic_crown_voxels(base, height: float, cbh: float, radius: float, size: float, fill: float,
                       rng: np.random.Generator) -> np.ndarray:
    """Centres of filled voxels of a cone-shaped crown (global lattice, cell origins at k·size)."""
    base = np.asarray(base, dtype=np.float64)
    lo = np.floor((base + [-radius, -radius, cbh]) / size).astype(np.int64)
    hi = np.ceil((base + [radius, radius, height]) / size).astype(np.int64)
    ii, jj, kk = np.meshgrid(*[np.arange(lo[d], hi[d]) for d in range(3)], indexing="ij")
    c = (np.stack([ii, jj, kk], axis=-1).reshape(-1, 3) + 0.5) * size
    rel = c - base
    zrel = (rel[:, 2] - cbh) / (height - cbh)
    rmax = radius * (1.0 - zrel)
    d = np.hypot(rel[:, 0], rel[:, 1])
    inside = (zrel >= 0) & (zrel <= 1) & (d <= rmax)
    # denser towards the crown surface (shell), sparser inside
    shell = np.clip(d / np.maximum(rmax, 1e-9), 0, 1)
    p = fill * (0.35 + 0.65 * shell)
    keep = inside & (rng.random(len(c)) < p)
    return c[keep]


def write_demo(out_dir, seed: int = 0, voxel_size: float = 0.25, ground_z: float = 0.0,
               half_extent: float = 20.0, name: str = "scene.yaml") -> Path:
    """Write the demo scene (``scene.yaml``, ``stem.obj``, ``crown.csv``) into ``out_dir``.

    Parameters
    ----------
    out_dir : str or Path
        Output folder.
    seed : int
        Seed of the crown's random occupancy.
    voxel_size : float
        Crown voxel size (m).
    ground_z : float
        Ground elevation.
    half_extent : float
        Half side of the square ground plane around the tree (m).
    name : str
        File name of the scene description in ``out_dir``.

    Returns
    -------
    Path
        The ``scene.yaml`` written.
    """
    if not voxel_size > 0:
        raise ConfigError(f"demo.voxel_size must be > 0, got {voxel_size!r}")
    out = Path(out_dir)
    rng = np.random.default_rng(seed)
    base = np.array([0.0, 0.0, ground_z])
    write_mesh(out / "stem.obj", stem_mesh(base, 24.0, 0.36))
    cen = conic_crown_voxels(base, 26.0, 6.0, 3.2, voxel_size, 0.45, rng)
    with atomic_path(out / "crown.csv") as tmp, open(tmp, "w") as fh:
        fh.write("x,y,z\n")
        np.savetxt(fh, cen, fmt="%.6f", delimiter=",")
    scene = {"parts": [
        {"id": 1, "type": "plane", "z": float(ground_z),
         "extent": [-half_extent, -half_extent, half_extent, half_extent], "reflectance": 0.25, "name": "ground"},
        {"id": 2, "type": "mesh", "path": "stem.obj", "reflectance": 0.3, "name": "stem"},
        {"id": 3, "type": "voxels", "path": "crown.csv", "size": float(voxel_size), "reflectance": 0.45,
         "classification": 5, "name": "crown"},
    ]}
    return write_text(out / name, yaml.safe_dump(scene, sort_keys=False))
