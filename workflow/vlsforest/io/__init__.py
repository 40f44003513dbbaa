"""Reading and writing the file formats vlsforest uses.

- :mod:`vlsforest.io.las` — LAS/LAZ point clouds (laspy + lazrs), with clear errors.
- :mod:`vlsforest.io.vox` — AMAPVox ``.vox`` voxel files.
- :mod:`vlsforest.io.mesh` — triangle meshes (OBJ, PLY).
"""

from vlsforest.io.las import PointCloud, read_las, write_las

__all__ = ["PointCloud", "read_las", "write_las"]
