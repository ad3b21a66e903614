"""What ``convert`` writes (:class:`ConvertConfig`); light, so the CLI reads it without torch or h5py."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from deliffas.data.subject_options import SubjectOptions
from deliffas.options import dask_target, int_list, non_negative_int, opt, positive_int, power_of_two

__all__ = ["ConvertConfig"]


@dataclass(frozen=True)
class ConvertConfig:
    """What ``convert`` writes."""
    format: str = opt("auto", help="capture format (auto = detected; an unknown name lists the registered ones)")
    frames: str | None = opt(None, help="A:B:STEP capture frames (a Python slice of frame indices; any part may be "
                                        "empty)", default_text="all")
    cameras: tuple[int, ...] | None = opt(None, help="calibration indices a,b,...", parse=int_list, default_text="all")
    sequences: tuple[str, ...] | None = None
    """Sequence folders to convert; None = those of ``training``/``testing`` present."""
    shard_frames: int = opt(10, help="frames per shard", parse=positive_int)
    jobs: int = opt(1, help="worker processes (spawned; 1 = in this process)", parse=positive_int)
    dask: str | None = opt(None, help="convert on Dask, one task per shard: a running scheduler (tcp://HOST:8786) "
                                      "or local:N (a LocalCluster of N worker processes on 127.0.0.1); OUT must be "
                                      "on a file system every worker shares and SUBJECT readable by them "
                                      "(docs/scale.md); replaces --jobs", parse=dask_target, metavar="ADDRESS|local:N",
                           default_text="no Dask")
    resume: bool = opt(False, help="keep complete shards of an interrupted run with the same configuration")
    overwrite: bool = opt(False, help="replace an existing conversion in OUT (or convert into a non-empty folder "
                                      "that holds none)")
    motions: tuple[str, ...] = opt((), help="pose parameters instead of the sequence's own: .motion (DDC) or AMASS "
                                            ".npz (SMPL) (SEQ default training; repeatable)", repeat=True,
                                   metavar="[SEQ=]FILE", default_text="none")
    meshes: tuple[str, ...] = opt((), help="tracked .meshes instead of the skinned template (SEQ default training; "
                                           "repeatable)", repeat=True, metavar="[SEQ=]FILE", default_text="none")
    template: str | None = opt(None, help="template variant folder (its .character + outer.obj), a .character, or "
                                          "an SMPL model .npz/.pkl (with --motions fitted to a DDC capture, or the "
                                          "capture's own SMPL poses)", default_text="the capture's own template")
    atlas_res: int = opt(256, help="normal-map side S, a power of two (the paper: 1024)", parse=power_of_two)
    offset_mm: float = opt(30.0, help="outer-surface offset d in mm (where no outer.obj gives per-vertex offsets)", flag="--offset")
    codec: str = opt("raw", help="raw (lossless gzip arrays) | png | jpeg:Q")
    window: int = opt(2, help="temporal window T: predecessors stored per frame (f, f-1, ..., f-T)", parse=non_negative_int)
    layout: Literal["auto", "images", "videos"] = opt("auto", help="where the frames are: images = image folders, "
                                                                   "videos = one video per camera, auto = images "
                                                                   "when present, else videos")
    skinning: Literal["dqs", "lbs"] = "dqs"
    """Skinning of the template."""
    test_cameras: tuple[int, ...] | None = opt(None, help="held-out cameras a,b,...", parse=int_list,
                                               default_text="SUBJECT/split.json or test_cameras.txt")
    gutter: int = 2
    """Texel-table gutter rings."""
    masks: str | None = opt(None, help="mask folder in each sequence folder (DDC: foregroundSegmentation, "
                                       "<cam>/image_c_<cam>_f_<frame>.png|jpg) replacing alpha/fg", metavar="SUBDIR",
                            default_text="the images' alpha or the fg videos")
    progress: bool = opt(True, help="no progress bar")
    check: bool = opt(True, help="convert even when the silhouette check (deliffas.data.check, on a few frames first) "
                                 "fails")

    def subject_options(self) -> SubjectOptions:
        """How to read the capture when ``convert`` is given a folder."""
        return SubjectOptions(template=self.template, skinning=self.skinning, sequences=self.sequences,
                              layout=self.layout, masks=self.masks, meshes=tuple(self.meshes),
                              motions=tuple(self.motions),
                              test_cameras=self.test_cameras)
