"""vlsforest: virtual laser scanning of voxelised forests, reproducing Weiser et al. (2021).

The package is layered; a module imports only modules of its own layer or of layers below it
(``[tool.importlinter]`` in ``pyproject.toml``, checked by ``tests/test_layers.py``):

==========  ==================================================================================
commands    :mod:`~vlsforest.cli` and :mod:`~vlsforest.commands`: the ``vlsforest <stage>``
            command line; nothing imports it
analysis    :mod:`~vlsforest.metrics`, :mod:`~vlsforest.stats`, :mod:`~vlsforest.report`,
            :mod:`~vlsforest.diagnose`, :mod:`~vlsforest.pad_validation`: what is computed
            from the stages' outputs
stages      :mod:`~vlsforest.synth`, :mod:`~vlsforest.segment`, :mod:`~vlsforest.stems`,
            :mod:`~vlsforest.pad`, :mod:`~vlsforest.voxels`, :mod:`~vlsforest.scene`,
            :mod:`~vlsforest.extract`, :mod:`~vlsforest.demo`: the study's processing steps,
            independent of each other (they meet in files); below them the tree-cell kernel
            of extraction
sim         :mod:`~vlsforest.sim`: the LiDAR simulator, which knows nothing of the study
io          :mod:`~vlsforest.io`: one reader and one writer per file kind
domain      :mod:`~vlsforest.domain` and :mod:`~vlsforest.errors`: the study's vocabulary
            (species groups, PAD settings, leaf angles, object ids, cube geometry), no I/O
==========  ==================================================================================

Each module exposes its own public functions; a name prefixed with an underscore is private to
its module (a private module, such as ``sim._voxelgrid``, to its package).
"""

from vlsforest.errors import ConfigError, InputDataError, VlsforestError

__version__ = "0.1.0"

__all__ = ["VlsforestError", "ConfigError", "InputDataError", "__version__"]
