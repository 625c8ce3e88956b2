"""physint: learning physical intuition for robotic manipulation, as a command-line toolkit."""

from importlib.metadata import PackageNotFoundError, version as _version

from .hookspecs import hookimpl

try:
    __version__ = _version("physint")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = ["hookimpl", "__version__"]
