"""Reading and writing the file formats vlsforest uses.

- :mod:`vlsforest.io.las` — LAS/LAZ point clouds (laspy + lazrs), with clear errors.
- :mod:`vlsforest.io.vox` — AMAPVox ``.vox`` voxel files.
- :mod:`vlsforest.io.mesh` — triangle meshes (OBJ, PLY).
"""

from vlsforest.io.las import PointCloud, read_las, write_las
from vlsforest.io.mesh import TriangleMesh, read_mesh, write_mesh
from vlsforest.io.vox import STANDARD_COLUMNS, VoxFile, make_vox, read_vox, write_vox

__all__ = ["PointCloud", "read_las", "write_las", "TriangleMesh", "read_mesh", "write_mesh",
           "STANDARD_COLUMNS", "VoxFile", "make_vox", "read_vox", "write_vox"]
