"""Reading and writing the file formats vlsforest uses.

- :mod:`vlsforest.io.las` — LAS/LAZ point clouds (laspy + lazrs), with clear errors.
- :mod:`vlsforest.io.vox` — AMAPVox ``.vox`` voxel files.
- :mod:`vlsforest.io.mesh` — triangle meshes (OBJ, PLY).
- :mod:`vlsforest.io.voxel_model` — voxel models (``.npz``) and their AMAPVox export.
- :mod:`vlsforest.io.npz` — deterministic ``.npz`` files and their validating loader.
- :mod:`vlsforest.io.yamlfile` — YAML files, with one-line errors.
- :mod:`vlsforest.io.atomic` — whole-or-nothing writes (temporary name + rename) and output path checks.
"""

from vlsforest.io.las import PointCloud, read_las, write_las
from vlsforest.io.mesh import TriangleMesh, read_mesh, write_mesh
from vlsforest.io.npz import ArraySpec, load_npz, save_npz
from vlsforest.io.vox import STANDARD_COLUMNS, VoxFile, make_vox, read_vox, write_vox
from vlsforest.io.voxel_model import VoxelModel, model_vox

__all__ = ["PointCloud", "read_las", "write_las", "TriangleMesh", "read_mesh", "write_mesh",
           "STANDARD_COLUMNS", "VoxFile", "make_vox", "read_vox", "write_vox", "VoxelModel", "model_vox",
           "save_npz", "load_npz", "ArraySpec"]
