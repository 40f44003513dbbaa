"""Reading and writing the file formats vlsforest uses.

- :mod:`vlsforest.io.las` — LAS/LAZ point clouds (laspy + lazrs), with clear errors.
- :mod:`vlsforest.io.vox` — AMAPVox ``.vox`` voxel files.
- :mod:`vlsforest.io.mesh` — triangle meshes (OBJ, PLY).
- :mod:`vlsforest.io.voxel_model` — voxel models (``.npz``) and their AMAPVox export.
- :mod:`vlsforest.io.npz` — deterministic ``.npz`` files and their validating loader.
- :mod:`vlsforest.io.yamlfile` — YAML files, with one-line errors.
- :mod:`vlsforest.io.csvfile` — CSV tables, with one-line errors.
- :mod:`vlsforest.io.atomic` — whole-or-nothing writes (temporary name + rename) and output path checks.
"""

from importlib import import_module
from types import MappingProxyType
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # what the names below resolve to, for type checkers and the API reference
    from vlsforest.io.csvfile import read_csv_table
    from vlsforest.io.las import PointCloud, read_las, write_las
    from vlsforest.io.mesh import TriangleMesh, read_mesh, write_mesh
    from vlsforest.io.npz import ArraySpec, load_npz, save_npz
    from vlsforest.io.vox import STANDARD_COLUMNS, VoxFile, make_vox, read_vox, write_vox
    from vlsforest.io.voxel_model import VoxelModel, model_vox

#: each name of ``__all__`` -> the submodule of :mod:`vlsforest.io` that defines it (read-only);
#: the package imports that module on the name's first use, so that a command that needs none of
#: them (or one) does not load laspy and pandas for the others
HOMES = MappingProxyType({
    "PointCloud": "las", "read_las": "las", "write_las": "las",
    "TriangleMesh": "mesh", "read_mesh": "mesh", "write_mesh": "mesh",
    "ArraySpec": "npz", "load_npz": "npz", "save_npz": "npz",
    "STANDARD_COLUMNS": "vox", "VoxFile": "vox", "make_vox": "vox", "read_vox": "vox", "write_vox": "vox",
    "VoxelModel": "voxel_model", "model_vox": "voxel_model",
    "read_csv_table": "csvfile",
})

__all__ = ["PointCloud", "read_las", "write_las", "TriangleMesh", "read_mesh", "write_mesh",
           "STANDARD_COLUMNS", "VoxFile", "make_vox", "read_vox", "write_vox", "VoxelModel", "model_vox",
           "save_npz", "load_npz", "ArraySpec", "read_csv_table"]


def __getattr__(name):
    home = HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.{home}"), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
