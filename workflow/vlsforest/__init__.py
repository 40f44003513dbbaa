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

The numba kernels are compiled with ``cache=True``. Numba keeps the cache in the first writable
of: ``NUMBA_CACHE_DIR``, the ``__pycache__`` folders beside the library's sources, the user's
cache folder (``$XDG_CACHE_HOME/numba``, default ``~/.cache/numba``). Where none of them can be
written (a read-only checkout and a read-only home), importing the package points
``NUMBA_CACHE_DIR`` at a temporary folder that is removed when the process ends: the kernels are
then compiled in every process instead of numba refusing to load them.
"""

import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path

from vlsforest.errors import ConfigError, InputDataError, VlsforestError

__version__ = "0.1.0"

__all__ = ["VlsforestError", "ConfigError", "InputDataError", "__version__"]


def _can_create_in(folder: Path) -> bool:
    """Whether a file can be made in ``folder`` (or, when it does not exist yet, in its nearest
    existing ancestor, where the folder would be created): a real try with an unnamed file."""
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def _numba_cache_fallback() -> None:
    """Give numba a temporary cache folder where none of its own cache places can be written."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    user_cache = Path(os.environ.get("XDG_CACHE_HOME") or Path("~/.cache").expanduser(), "numba")
    if _can_create_in(Path(__file__).parent / "__pycache__") or _can_create_in(user_cache):
        return
    try:
        folder = tempfile.mkdtemp(prefix="vlsforest-numba-")
    except OSError:  # nowhere to write at all: numba then names the problem itself
        return
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    os.environ["NUMBA_CACHE_DIR"] = folder  # spawned worker processes share it
    config = sys.modules.get("numba.core.config")
    if config is not None:  # numba imported already: its settings were read from the environment
        config.CACHE_DIR = folder


_numba_cache_fallback()
