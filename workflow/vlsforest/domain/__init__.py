"""The study's vocabulary: the lowest layer of vlsforest, free of I/O.

* :mod:`~vlsforest.domain.species` — species → group (broadleaf / conifer), the leaf angle
  distributions and the PAD settings (leaf angle distribution, PADmax) of each group;
* :mod:`~vlsforest.domain.labels` — object ids of a scene (ground, surrounding trees, the stem
  and crown of each target tree);
* :mod:`~vlsforest.domain.cubes` — cube geometry on the voxel lattice: PAD-scaled cube sides
  and the triangles of axis-aligned cubes.

Every other layer (io, sim, the processing stages, the analysis, the commands) may import it;
it imports nothing of vlsforest but :mod:`vlsforest.errors`.
"""
