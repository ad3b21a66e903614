"""Deprecated: moved to :mod:`deliffas.io.formats.dynacap.calibration` (this module re-exports it for one release)."""

import warnings

from deliffas.io.formats.dynacap.calibration import *  # noqa: F401,F403 - the old names, kept for one release
from deliffas.io.formats.dynacap.calibration import __all__  # noqa: F401

warnings.warn("deliffas.io.calibration moved to deliffas.io.formats.dynacap.calibration (or import its readers from deliffas.io); "
              "the old module goes in the next release", DeprecationWarning, stacklevel=2)
