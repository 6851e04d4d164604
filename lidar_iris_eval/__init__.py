"""liris: faithful, fast evaluation of LiDAR loop-closure descriptors."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("lidar_iris_eval")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
