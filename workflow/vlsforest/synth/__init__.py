"""Synthetic trees for the embedded virtual Bretten forest.

* :mod:`~vlsforest.synth.species` — species parameter sets, :class:`TreeParams`, draws from the
  real Bretten distributions (:func:`sample_tree_params`) and the study's 30 targets
  (:func:`target_tree_params`);
* :mod:`~vlsforest.synth.trees` — :func:`generate_tree` → :class:`TreeGeometry` (triangle mesh
  with organ labels, closed stem mesh, truth measured on the geometry);
* :mod:`~vlsforest.synth.plant_area` — :func:`true_plant_area`, the exact one-sided plant area per
  voxel on any grid (validation of PAD estimates);
* :mod:`~vlsforest.synth.ground` — :class:`GroundSurface`, the gently rough plot terrain;
* :mod:`~vlsforest.synth.forest` — plot layouts of the virtual Bretten forest
  (:func:`forest_from_config`, one plot's :func:`plot_layout`, :class:`PlotLayout`,
  :class:`TreeSpec`), their geometry (:func:`generate_plot_trees`) and truth (:func:`truth_table`).
"""

from vlsforest.synth.forest import (
    DEFAULT_FOREST,
    QUICK_FOREST,
    PlotLayout,
    TreeSpec,
    forest_from_config,
    generate_plot_trees,
    plot_layout,
    stem_meshes,
    truth_table,
)
from vlsforest.synth.ground import GroundSurface
from vlsforest.synth.plant_area import PlantAreaGrid, true_plant_area
from vlsforest.synth.species import (
    SPECIES,
    TABLE1,
    SpeciesParams,
    TreeParams,
    get_species,
    sample_tree_params,
    target_tree_params,
)
from vlsforest.synth.trees import (
    ORGAN_BRANCH,
    ORGAN_FOLIAGE,
    ORGAN_STEM,
    TreeGeometry,
    TriMesh,
    generate_tree,
)

__all__ = [
    "SPECIES", "TABLE1", "SpeciesParams", "TreeParams", "get_species",
    "sample_tree_params", "target_tree_params", "TreeGeometry", "TriMesh", "generate_tree",
    "ORGAN_STEM", "ORGAN_BRANCH", "ORGAN_FOLIAGE", "PlantAreaGrid", "true_plant_area",
    "GroundSurface", "DEFAULT_FOREST", "QUICK_FOREST", "PlotLayout", "TreeSpec",
    "forest_from_config", "plot_layout", "generate_plot_trees", "truth_table", "stem_meshes",
]
