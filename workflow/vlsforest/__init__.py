"""vlsforest: virtual laser scanning of voxelised forests, reproducing Weiser et al. (2021).

The public API is deliberately small; stage modules (``sim``, ``io``, ``metrics`` …) expose
their own public functions, everything prefixed with an underscore is private.
"""

from vlsforest.errors import ConfigError, InputDataError, VlsforestError

__version__ = "0.1.0"

__all__ = ["VlsforestError", "ConfigError", "InputDataError", "__version__"]
