"""Voxel models as files: the cubes of one voxel method for one plot (``.npz``).

A :class:`VoxelModel` holds opaque cubes on the global lattice of its cell size (see
:mod:`vlsforest.voxels`, which builds them); the simulator reads it as a scene part and the
scene assembly writes it per target crown and for the surrounding trees.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlsforest.errors import ConfigError, InputDataError
from vlsforest.io.npz import ArraySpec, load_npz, save_npz

__all__ = ["VoxelModel", "model_vox", "load_crowns", "VOXEL_MODEL_SPEC", "CROWNS_SPEC"]


@dataclass
class VoxelModel:
    """Opaque cubes on a global lattice.

    Attributes
    ----------
    size : float
        Lattice cell size ``a0`` (m); cell ``ijk`` spans ``ijk·size`` to ``(ijk+1)·size``.
    ijk : ndarray int64 (n, 3)
        Cells, sorted lexicographically, unique.
    owner : ndarray int64 (n,)
        Tree id owning each cell (the label most of its points carry; ties → the smallest id).
    half : ndarray float64 (n,) or None
        Half side of each cube; None = full cells.
    centre : ndarray float64 (n, 3) or None
        Cube centres; None = cell centres.
    pad : ndarray float64 (n,) or None
        Plant area density used for the cube size (scaled models).
    """

    size: float
    ijk: np.ndarray
    owner: np.ndarray
    half: np.ndarray | None = None
    centre: np.ndarray | None = None
    pad: np.ndarray | None = None

    def __post_init__(self):
        if not (np.isfinite(self.size) and self.size > 0):
            raise ConfigError(f"voxel size must be > 0, got {self.size!r}")
        self.ijk = np.asarray(self.ijk, dtype=np.int64).reshape(-1, 3)
        self.owner = np.asarray(self.owner, dtype=np.int64).reshape(-1)
        if len(self.owner) != len(self.ijk):
            raise InputDataError("voxel model: one owner per cell required")

    @property
    def n_voxels(self) -> int:
        """Number of cubes."""
        return len(self.ijk)

    def centres(self) -> np.ndarray:
        """Cube centres (n, 3)."""
        if self.centre is not None:
            return self.centre
        return (self.ijk + 0.5) * self.size

    def sides(self) -> np.ndarray:
        """Cube side lengths (n,)."""
        if self.half is None:
            return np.full(len(self.ijk), self.size)
        return 2.0 * self.half

    def subset(self, mask) -> "VoxelModel":
        """The cubes selected by a boolean mask or index array."""
        def sel(a):
            return None if a is None else a[mask]

        return VoxelModel(self.size, self.ijk[mask], self.owner[mask], sel(self.half), sel(self.centre),
                          sel(self.pad))

    def save(self, path) -> Path:
        """Write as ``.npz`` (deterministic bytes)."""
        arrays = {"size": np.float64(self.size), "ijk": self.ijk, "owner": self.owner}
        for name in ("half", "centre", "pad"):
            v = getattr(self, name)
            if v is not None:
                arrays[name] = np.asarray(v, dtype=np.float64)
        return save_npz(path, arrays)

    @classmethod
    def load(cls, path) -> "VoxelModel":
        """Read and validate a model written by :meth:`save` (:data:`VOXEL_MODEL_SPEC`).

        Raises
        ------
        InputDataError
            For a file that is not a complete, consistent voxel model; names the file and array.
        """
        path = Path(path)
        d = load_npz(path, VOXEL_MODEL_SPEC, "voxel model")
        size = float(d["size"])
        if not size > 0:
            raise InputDataError(f"{path}: array 'size' must be > 0, got {size!r}")
        if "half" in d and np.any((d["half"] < 0) | (d["half"] > 0.5 * size * (1 + 1e-9))):
            raise InputDataError(f"{path}: array 'half' holds cube half sizes outside [0, size/2]")
        return cls(size, d["ijk"], d["owner"], d.get("half"), d.get("centre"), d.get("pad"))


#: the arrays of a voxel model file ("n": one row per cube)
VOXEL_MODEL_SPEC = {"size": ArraySpec("f", ()), "ijk": ArraySpec("iu", ("n", 3)), "owner": ArraySpec("iu", ("n",)),
                    "half": ArraySpec("f", ("n",), required=False), "centre": ArraySpec("f", ("n", 3), required=False),
                    "pad": ArraySpec("f", ("n",), required=False, finite=False)}
#: the arrays of a crowns file (``vlsforest scene crowns``: points to voxelise and their tree ids)
CROWNS_SPEC = {"xyz": ArraySpec("f", ("n", 3)), "owner": ArraySpec("iu", ("n",))}


def load_crowns(path) -> tuple[np.ndarray, np.ndarray]:
    """Read and validate a crowns file: ``(xyz (n, 3) float64, owner (n,) int64)``.

    Raises
    ------
    InputDataError
        For a file that is not a complete crowns file, or one without points; names the file.
    """
    d = load_npz(path, CROWNS_SPEC, "crowns")
    if len(d["xyz"]) == 0:
        raise InputDataError(f"{path}: the crowns file holds no points")
    return d["xyz"].astype(np.float64), d["owner"].astype(np.int64)


def model_vox(model: VoxelModel, pad_max: float | None):
    """An AMAPVox voxel file of a voxel model (HELIOS++ reads it as a scene part).

    Parameters
    ----------
    model : VoxelModel
        Fixed cubes, or PAD-scaled cubes centred in their cells.
    pad_max : float or None
        None writes the cells only (HELIOS++ ``fixed`` mode). A value writes a ``PadBVTotal``
        column and ``#max_pad`` such that HELIOS++'s ``scaled`` mode, side
        ``size · (PAD / pad_max)^0.5``, gives each cube its side.

    Returns
    -------
    vlsforest.io.vox.VoxFile
        On a local grid whose minimum corner is the model's lowest cell.
    """
    from vlsforest.io.vox import make_vox

    lo = model.ijk.min(axis=0)
    cols = {}
    if pad_max is not None:
        # PAD' such that a0·(PAD'/pad_max)^0.5 equals our side: (side/a0)² · pad_max
        cols["PadBVTotal"] = (model.sides() / model.size) ** 2 * pad_max
    return make_vox(model.ijk - lo, model.size, lo * model.size, cols, max_pad=pad_max,
                    header={"type": "TLS", "build-version": "1.4.3"})
