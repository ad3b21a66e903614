"""What ``ingest`` does (:class:`IngestConfig`); light, so the CLI reads it without torch or numpy."""

from __future__ import annotations

from dataclasses import dataclass

from deliffas.options import check_fields, non_negative_float, opt, positive_int

__all__ = ["IngestConfig", "INGEST_MARKER", "INGEST_EXTRA"]

INGEST_MARKER = "ingest_report.json"
"""The file ``ingest`` writes last into a subject: its presence marks a finished ingest."""
INGEST_EXTRA = "ingest"
"""The pip extra that brings the detector (``pip install 'deliffas[ingest]'``)."""


def _size_or_long_side(text: str) -> tuple[int, int] | int:
    """``WxH`` or one number N (the long side; the other keeps the aspect ratio)."""
    t = text.strip().lower()
    if "x" in t:
        w, _, h = t.partition("x")
        size = (positive_int(w), positive_int(h))
        return size
    return positive_int(t)


@dataclass(frozen=True)
class IngestConfig:
    """What ``ingest`` reads and writes (docs/own-recording.md)."""
    recording: str = opt(help="recording folder: one video per camera (in videos/ or the folder itself: "
                              ".mp4 .avi .mov .mkv .webm) or one image folder per camera (images/CAM/), and a "
                              "calibration",
                         flag="")
    out: str = opt(help="subject folder to write (DynaCap layout, read by check/convert unchanged)", flag="--out")
    calibration: str | None = opt(None, help="calibration file (any format `deliffas cameras` reads)",
                                  default_text="the one found in RECORDING")
    frames: str | None = opt(None, help="A:B:STEP frames of the streams (stop exclusive)", default_text="all")
    cameras: str | None = opt(None, help="calibration camera names to use, NAME,NAME,...", default_text="all")
    size: tuple[int, int] | int = opt(960, help="image size written: WxH, or N = the long side (aspect kept)",
                                      parse=_size_or_long_side, metavar="WxH|N")
    test_cameras: int = opt(1, help="cameras held out for testing (the last ones of the calibration)",
                            parse=positive_int)
    test_frames: float = opt(0.2, help="fraction of the frames (the last ones) written as the novel-pose 'testing' "
                                       "sequence; 0 = none", parse=non_negative_float)
    body_model: str = opt("procedural", help="SMPL model file (.npz/.pkl, official layout) or 'procedural' (the "
                                             "license-free body in SMPL layout)", metavar="MODEL|procedural")
    min_views: int = opt(2, help="views a keypoint needs to be triangulated", parse=positive_int)
    min_frames: int = opt(10, help="fewest usable frames (a person in >= 2 views) before the ingest stops",
                          parse=positive_int)
    overlays: int = opt(4, help="frames with overlay pictures (mask and fitted body over the image)",
                        parse=positive_int)
    fit_iters: int = opt(300, help="steps of the body fit's keypoint stage (its silhouette stage takes half as many)",
                         parse=positive_int)
    seed: int = opt(0, help="random seed of the body fit's pixel samples")
    resume: bool = opt(False, help="continue an interrupted ingest in --out (finished stages are kept)")
    overwrite: bool = opt(False, help="replace an earlier ingest in --out")
    progress: bool = opt(True, help="no progress bars")

    def __post_init__(self) -> None:
        check_fields(self)  # each option's own check, as on the command line
