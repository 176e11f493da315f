"""fwk: deep 3D morphable models of registered face meshes."""
from . import _waiting

_waiting.apply()  # first: idle OpenMP/BLAS threads sleep, set before torch or NumPy load (fwk._waiting)

from importlib.metadata import PackageNotFoundError, version  # noqa: E402

try:
    __version__ = version("fwk")
except PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+source"

from .errors import DataError, FwkError, RecipeError, TopologyError  # noqa: E402

__all__ = ["__version__", "FwkError", "RecipeError", "DataError", "TopologyError"]
