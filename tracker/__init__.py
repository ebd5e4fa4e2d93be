"""Estimation of the bending plane and the online loop (models <- tracker <- replay)."""

from importlib import metadata

try:
    __version__ = metadata.version("cathtrack")
except metadata.PackageNotFoundError:  # a source tree that is not installed
    __version__ = "0+unknown"
