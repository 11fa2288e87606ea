"""pwlreg's HTTP service: routing, validation, job store, queue and storage around
``core.pipeline.register``."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("pwlreg")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.1.0"
