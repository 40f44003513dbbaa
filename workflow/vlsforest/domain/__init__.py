"""The study's vocabulary: the lowest layer of vlsforest, free of I/O.

* :mod:`~vlsforest.domain.species` — species → group (broadleaf / conifer) and the PAD
  settings (leaf angle distribution, PADmax) of each group;
* :mod:`~vlsforest.domain.leaf_angles` — the leaf angle distributions, their densities and the
  projection function G(θ) that PAD estimation and PAD-scaled voxels share;
* :mod:`~vlsforest.domain.labels` — object ids of a scene (ground, surrounding trees, the stem
  and crown of each target tree);
* :mod:`~vlsforest.domain.cubes` — cube geometry on the voxel lattice: PAD-scaled cube sides
  and the triangles of axis-aligned cubes.

Every other layer (io, sim, the processing stages, the analysis, the commands) may import it;
it imports nothing of vlsforest but :mod:`vlsforest.errors`.
"""
