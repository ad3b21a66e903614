"""Deprecated: moved to :mod:`deliffas.io.formats.dynacap.meshes` (this module re-exports it for one release)."""

import warnings

from deliffas.io.formats.dynacap.meshes import *  # noqa: F401,F403 - the old names, kept for one release
from deliffas.io.formats.dynacap.meshes import __all__  # noqa: F401

warnings.warn("deliffas.io.meshes moved to deliffas.io.formats.dynacap.meshes (or import its readers from deliffas.io); "
              "the old module goes in the next release", DeprecationWarning, stacklevel=2)
