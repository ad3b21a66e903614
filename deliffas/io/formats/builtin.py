"""The built-in capture formats' cameras, registered in detection order: one line per format.

``deliffas.io.format_registry`` imports this module before its first registration or lookup, so the
order below is the order in which camera files are detected and formats are listed (ZJU-MoCap before
EasyMocap: ZJU-MoCap folders may also hold ``intri.yml``).
"""

from deliffas.io.format_registry import register_capture_format
from deliffas.io.formats import (actorshq, calib_toml, colmap, dna_rendering, easymocap, nerfstudio, panoptic,
                                 qualisys, thuman4, zju_mocap)
from deliffas.io.formats.dynacap import calibration

register_capture_format(calibration.FORMAT)
register_capture_format(colmap.FORMAT)
register_capture_format(zju_mocap.FORMAT)
register_capture_format(easymocap.FORMAT)
register_capture_format(nerfstudio.FORMAT)
register_capture_format(thuman4.FORMAT)
register_capture_format(actorshq.FORMAT)
register_capture_format(dna_rendering.FORMAT)
register_capture_format(calib_toml.FORMAT)
register_capture_format(qualisys.FORMAT)
register_capture_format(panoptic.FORMAT)
