"""What ``ingest`` does (:class:`IngestConfig`); light, so the CLI reads it without torch or numpy."""

from __future__ import annotations

from dataclasses import dataclass

from deliffas.options import non_negative_float, opt, positive_int

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
    recording: str = opt(help="recording folder: one video (or one image folder) per camera and a calibration",
                         flag="")
    """Recording folder: videos in ``videos/`` or the folder itself (``.mp4 .avi .mov .mkv .webm``), or one
    image folder per camera (``images/<cam>/``), and a calibration in any format deliffas reads."""
    out: str = opt(help="subject folder to write (DynaCap layout, read by check/convert unchanged)", flag="--out")
    """Subject folder to write."""
    calibration: str | None = opt(None, help="calibration file (any format `deliffas cameras` reads)",
                                  default_text="the one found in RECORDING")
    """Calibration file; None = detected in the recording folder (``deliffas.io.camera_formats``)."""
    frames: str | None = opt(None, help="A:B:STEP frames of the streams (stop exclusive)", default_text="all")
    """``A:B:STEP`` frame indices of the streams (stop exclusive); None = every frame."""
    cameras: str | None = opt(None, help="calibration camera names to use, NAME,NAME,...", default_text="all")
    """Calibration camera names to use, comma separated; None = every camera of the calibration."""
    size: tuple[int, int] | int = opt(960, help="image size written: WxH, or N = the long side (aspect kept)",
                                      parse=_size_or_long_side, metavar="WxH|N")
    """Size of the images written and detected on: ``(W, H)`` or the long side in pixels (aspect kept)."""
    test_cameras: int = opt(1, help="cameras held out for testing (the last ones of the calibration)",
                            parse=positive_int)
    """Cameras held out as the test split (the last ones of the calibration order)."""
    test_frames: float = opt(0.2, help="fraction of the frames (the last ones) written as the novel-pose 'testing' "
                                       "sequence; 0 = none", parse=non_negative_float)
    """Fraction of the frames, at the end, written as the ``testing`` sequence (novel poses); 0 = none."""
    body_model: str = opt("procedural", help="SMPL model file (.npz/.pkl, official layout) or 'procedural' (the "
                                             "license-free body in SMPL layout)", metavar="MODEL|procedural")
    """An SMPL model file or ``"procedural"``; copied into the subject's ``body/``."""
    min_views: int = opt(2, help="views a keypoint needs to be triangulated", parse=positive_int)
    """Views with a detection a 3-D keypoint needs."""
    min_frames: int = opt(10, help="fewest usable frames (a person in >= 2 views) before the ingest stops",
                          parse=positive_int)
    """Fewest usable frames; fewer is an error."""
    overlays: int = opt(4, help="frames with overlay pictures (mask and fitted body over the image)",
                        parse=positive_int)
    """Frames drawn as overlays (evenly spaced), every camera."""
    fit_iters: int = opt(300, help="steps of the body fit's keypoint stage (its silhouette stage takes half as many)",
                         parse=positive_int)
    """Adam steps of the body fit's keypoint stage; the silhouette stage takes half as many."""
    seed: int = opt(0, help="random seed of the body fit's pixel samples")
    """Seeds the silhouette term's pixel samples."""
    resume: bool = opt(False, help="continue an interrupted ingest in --out (finished stages are kept)")
    """Continue an interrupted ingest: stages whose results are in ``--out/.ingest/`` are not run again."""
    overwrite: bool = opt(False, help="replace an earlier ingest in --out")
    """Replace an earlier ingest (a folder holding ``ingest_report.json``)."""
    progress: bool = opt(True, help="no progress bars")
    """Show tqdm progress bars."""
