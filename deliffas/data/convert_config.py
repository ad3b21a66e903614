"""What ``convert`` writes (:class:`ConvertConfig`); light, so the CLI reads it without torch or h5py."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from deliffas.options import dask_target, int_list, non_negative_int, opt, positive_int, power_of_two

if TYPE_CHECKING:
    from deliffas.data.subjects import SubjectOptions

__all__ = ["ConvertConfig"]


@dataclass(frozen=True)
class ConvertConfig:
    """What ``convert`` writes."""
    format: str = opt("auto", help="capture format (auto = detected; an unknown name lists the registered ones)")
    """Capture format (``deliffas.data.subjects.subject_format_names()``); auto = detected."""
    frames: str | None = opt(None, help="A:B:STEP capture frames", default_text="all")
    """``A:B:STEP`` (Python slice of capture frame indices, any part may be empty); None = every frame."""
    cameras: tuple[int, ...] | None = opt(None, help="calibration indices a,b,...", parse=int_list, default_text="all")
    """Calibration indices to convert; None = every camera."""
    sequences: tuple[str, ...] | None = None
    """Sequence folders to convert; None = those of ``training``/``testing`` present."""
    shard_frames: int = opt(10, help="frames per shard", parse=positive_int)
    """Selected frames per shard."""
    jobs: int = opt(1, help="worker processes", parse=positive_int)
    """Worker processes (spawned); 1 = in this process."""
    dask: str | None = opt(None, help="convert on Dask, one task per shard: a running scheduler (tcp://HOST:8786) "
                                      "or local:N (a LocalCluster of N worker processes on 127.0.0.1); OUT must be "
                                      "on a file system every worker shares and SUBJECT readable by them "
                                      "(docs/scale.md); replaces --jobs", parse=dask_target, metavar="ADDRESS|local:N",
                           default_text="no Dask")
    """Convert on Dask instead: a scheduler address (``tcp://HOST:8786``) or ``local:N`` (a LocalCluster of N
    worker processes); OUT must be on a file system the workers share, the subject readable by them."""
    resume: bool = opt(False, help="keep complete shards of an interrupted run")
    """Keep complete shards of an earlier run with the same configuration."""
    overwrite: bool = opt(False, help="replace an existing conversion in OUT (or convert into a non-empty folder "
                                      "that holds none)")
    """Delete an existing conversion in ``out_dir`` first."""
    motions: tuple[str, ...] = opt((), help="pose parameters instead of the sequence's own: .motion (DDC) or AMASS "
                                            ".npz (SMPL) (SEQ default training; repeatable)", repeat=True,
                                   metavar="[SEQ=]FILE", default_text="none")
    """Pose parameters ``[SEQUENCE=]FILE`` instead of the sequence's own (e.g. SMPL fitted to a DDC capture)."""
    meshes: tuple[str, ...] = opt((), help="tracked .meshes instead of the skinned template (SEQ default training; "
                                           "repeatable)", repeat=True, metavar="[SEQ=]FILE", default_text="none")
    """Tracked surfaces ``[SEQUENCE=]FILE.meshes`` (default sequence: training) instead of the skinned template."""
    template: str | None = opt(None, help="template variant folder (its .character + outer.obj), a .character, or "
                                          "an SMPL model .npz/.pkl (with --motions fitted to a DDC capture, or the "
                                          "capture's own SMPL poses)", default_text="the capture's own template")
    """A template variant folder (its ``.character`` + optional ``outer.obj``) or ``.character`` file."""
    atlas_res: int = opt(256, help="normal-map side S, a power of two (the paper: 1024)", parse=power_of_two)
    """S, the normal-map side (the paper uses 1024)."""
    offset_mm: float = opt(30.0, help="outer-surface offset d in mm", flag="--offset")
    """d of the outer surface (when no ``outer.obj`` gives per-vertex offsets)."""
    codec: str = opt("raw", help="raw (lossless) | png | jpeg:Q")
    """Image codec: ``raw`` (lossless gzip arrays), ``png`` or ``jpeg:Q``."""
    window: int = opt(2, help="temporal window T stored per frame", parse=non_negative_int)
    """T: predecessors stored per frame for temporal normal maps (f, f-1, ..., f-T)."""
    layout: Literal["auto", "images", "videos"] = opt("auto", help="where the frames are: images = image folders, "
                                                                   "videos = one video per camera, auto = images "
                                                                   "when present, else videos")
    """Frame layout of the subject (auto: images when present, else videos)."""
    skinning: Literal["dqs", "lbs"] = "dqs"
    """Skinning of the template."""
    test_cameras: tuple[int, ...] | None = opt(None, help="held-out cameras a,b,...", parse=int_list,
                                               default_text="SUBJECT/split.json or test_cameras.txt")
    """Held-out cameras; None = the subject's ``split.json`` / ``test_cameras.txt`` (or none)."""
    gutter: int = 2
    """Texel-table gutter rings."""
    masks: str | None = opt(None, help="DDC mask folder in each sequence folder (<cam>/image_c_<cam>_f_<frame>"
                                       ".png|jpg) replacing alpha/fg", metavar="SUBDIR",
                            default_text="the images' alpha or the fg videos")
    """Mask folder inside each sequence folder (e.g. ``foregroundSegmentation``) replacing alpha / fg videos."""
    progress: bool = opt(True, help="no progress bar")
    """Show a tqdm progress bar."""
    check: bool = opt(True, help="convert even when the silhouette check fails")
    """Run the silhouette check (``deliffas.data.check``) on a few frames first and refuse a failing subject."""

    def subject_options(self) -> SubjectOptions:
        """How to read the capture when ``convert`` is given a folder."""
        from deliffas.data.subjects import SubjectOptions  # imported here: the CLI reads this module (--help)

        return SubjectOptions(template=self.template, skinning=self.skinning, sequences=self.sequences,
                              layout=self.layout, masks=self.masks, meshes=tuple(self.meshes),
                              motions=tuple(self.motions),
                              test_cameras=self.test_cameras)
