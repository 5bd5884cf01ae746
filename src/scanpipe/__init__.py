"""scanpipe: a 2-D laser scanner on a stepper turntable plus a camera, to a textured 3-D model."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("scanpipe")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0"

__all__ = ["__version__"]
