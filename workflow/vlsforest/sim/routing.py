"""Which back end traces each voxel set: Embree (12 triangles per cube) or the sparse voxel grid.

A scene's ``voxel_backend`` is ``embree`` or ``grid`` (every voxel set to that back end) or
``auto``: the voxel sets of one lattice (same cell size, congruent origin) all go to one back end,
chosen by the lattice's number of cubes and, when known, the number of rays to trace
(:func:`route_voxels`). Both back ends give the same hits up to rays that graze a cube edge or
corner.

The constants are read at each call, so they can be changed for a test or a benchmark.
"""

from __future__ import annotations

import math

from vlsforest.errors import ConfigError

#: the values of a scene's ``voxel_backend``
VOXEL_BACKENDS = ("auto", "embree", "grid")

#: without a number of rays, ``auto`` gives a lattice to Embree as 12 triangles per cube when it
#: holds up to this many cubes in all, else all of them to one sparse grid. Embree pays ≈ 6 µs
#: per cube to build and then traces faster; the grid builds in ≈ 0.5 µs per cube, and one grid
#: per lattice beats Embree plus a grid for the same crowns (``benchmarks/bench_embree_build.py``,
#: ``benchmarks/bench_sim.py``).
EMBREE_VOXEL_LIMIT = 300_000
#: with the number of rays known (:meth:`vlsforest.sim.scene.Scene.plan_for_rays`; the simulator
#: estimates it from the survey before tracing), ``auto`` weighs the Embree build
#: (:data:`EMBREE_BUILD_S_PER_CUBE`) against what Embree saves per ray over the grid
#: (:data:`EMBREE_SAVES_S_PER_RAY` at 0.25 m cells, more in finer lattices, where the grid walks
#: more cells: · (0.25 m / h)^0.6), with a margin of :data:`EMBREE_BUILD_MARGIN` for the build,
#: and never sends more than this many cubes of one lattice to Embree (≈ 1 kB each, built piece
#: by piece, :meth:`vlsforest.sim.scene_geometry.VoxelGeometry.triangle_chunks`): a dense
#: airborne flight traces fine crowns faster in Embree, a sparse one in the grid
#: (``benchmarks/bench_sim.py``).
EMBREE_VOXEL_MAX = 4_000_000
#: Embree's build time per cube (s; ``benchmarks/bench_embree_build.py``)
EMBREE_BUILD_S_PER_CUBE = 6e-6
#: the time Embree saves per ray over the grid in a lattice of 0.25 m cells (s)
EMBREE_SAVES_S_PER_RAY = 0.16e-6
#: the factor on the build time a lattice's rays must save to go to Embree
EMBREE_BUILD_MARGIN = 1.25


def check_backend(voxel_backend: str) -> str:
    """``voxel_backend`` if it is one of :data:`VOXEL_BACKENDS`, else a :class:`ConfigError`."""
    if voxel_backend not in VOXEL_BACKENDS:
        raise ConfigError(f"voxel_backend must be 'auto', 'embree' or 'grid', got {voxel_backend!r}")
    return voxel_backend


def check_expected_rays(n_rays) -> float:
    """``n_rays`` as a float if it is finite and ≥ 0, else a :class:`ConfigError`."""
    n = float(n_rays)
    if not math.isfinite(n) or n < 0:
        raise ConfigError(f"plan_for_rays: expected number of rays must be finite and >= 0, got {n_rays!r}")
    return n


def embree_pays(n_cubes: int, size: float, expected_rays: float | None = None) -> bool:
    """``auto``'s choice for one lattice: whether its cubes go to Embree.

    Parameters
    ----------
    n_cubes : int
        Cells of all voxel sets on the lattice.
    size : float
        The lattice's cell size (m).
    expected_rays : float, optional
        Rays to trace; None: unknown (then the lattice goes to Embree up to
        :data:`EMBREE_VOXEL_LIMIT` cubes).

    Returns
    -------
    bool
    """
    if expected_rays is None:
        return n_cubes <= EMBREE_VOXEL_LIMIT
    if n_cubes > EMBREE_VOXEL_MAX:
        return False
    saves = expected_rays * EMBREE_SAVES_S_PER_RAY * (0.25 / size) ** 0.6
    return saves > EMBREE_BUILD_MARGIN * EMBREE_BUILD_S_PER_CUBE * n_cubes


def route_voxels(voxels: list, voxel_backend: str, expected_rays: float | None = None) -> list[bool]:
    """Per voxel set, whether Embree traces it (else a voxel grid).

    Parameters
    ----------
    voxels : list of vlsforest.sim.scene_geometry.VoxelGeometry
        The scene's voxel sets.
    voxel_backend : {"auto", "embree", "grid"}
        The scene's choice.
    expected_rays : float, optional
        Rays to trace (``auto`` only; see :func:`embree_pays`).

    Returns
    -------
    list of bool
        In the order of ``voxels``; the sets of one lattice share their answer under ``auto``.
    """
    if voxel_backend != "auto":
        return [voxel_backend == "embree"] * len(voxels)
    keys = [v.lattice_key for v in voxels]
    cells: dict[tuple, int] = {}
    for k, v in zip(keys, voxels):
        cells[k] = cells.get(k, 0) + len(v.ijk)
    return [embree_pays(cells[k], k[0], expected_rays) for k in keys]
