"""``ingest``: a raw calibrated multi-view recording -> a DynaCap subject with masks and a fitted body per frame.

Stages (docs/own-recording.md): read the calibration and match the streams to its cameras; per camera decode,
undistort and resize the frames and detect the person (mask + 2-D keypoints, :mod:`.detect`); triangulate the
keypoints (:func:`deliffas.geometry.triangulate.triangulate`); keep the parts of each mask where the person
projects (:mod:`.masks`); fit the body model (one shape, a pose per frame) to the 3-D keypoints and the
silhouettes (:func:`deliffas.geometry.body_fit.fit_body`); write the subject, ``ingest_report.json`` and overlay
pictures (:mod:`.write`, :mod:`.report`).
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from deliffas.io.camera_formats import read_cameras
from deliffas.io.infra.files import claim_output
from deliffas.io.infra.text_lines import write_text_atomic
from deliffas.io.recording import check_streams, find_streams, match_streams, parse_frame_range
from deliffas.data.ingest.config import INGEST_MARKER, IngestConfig
from deliffas.data.ingest.detect import require_detector
from deliffas.data.ingest.frames import plan_frames
from deliffas.data.ingest import stages
from deliffas.data.ingest.fit_stage import fit_stage, prepare_body, triangulate_stage, write_fitted_body
from deliffas.data.ingest.report import write_outputs

__all__ = ["ingest", "IngestResult", "find_calibration"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class IngestResult:
    """What ``ingest`` wrote: the subject folder, its report (the dict of ``ingest_report.json``)."""
    out: Path
    report: dict = field(repr=False)


def find_calibration(root: Path) -> Path:
    """The calibration of a recording folder: the folder itself, ``calibration/``, or one file in either.

    Raises:
        FileNotFoundError: none found, saying to pass ``--calibration``.
    """
    candidates = [root, root / "calibration"]
    for d in (root, root / "calibration"):
        if d.is_dir():
            candidates += sorted(p for p in d.iterdir() if p.is_file())
    for p in candidates:
        if not p.exists():
            continue
        try:
            read_cameras(p)
            return p
        except (ValueError, OSError):
            continue
    raise FileNotFoundError(f"{root}: no calibration found (in the folder or calibration/); pass --calibration FILE "
                            "(any format 'deliffas cameras' reads)")


def _select_cameras(cameras: list, names: str | None, where: Path) -> list:
    if not names:
        return cameras
    wanted = [n.strip() for n in names.split(",") if n.strip()]
    by_name = {c.name: c for c in cameras}
    unknown = [n for n in wanted if n not in by_name]
    if unknown:
        raise ValueError(f"{where}: --cameras names {unknown} that the calibration lacks; it has "
                         f"{sorted(by_name)}")
    return [by_name[n] for n in wanted]


def _work_config(config: IngestConfig, calib: Path) -> dict:
    """What an ingest's intermediate results depend on (``--resume`` refuses another)."""
    return {"recording": str(Path(config.recording).resolve()), "calibration": str(calib.resolve()),
            "frames": config.frames, "cameras": config.cameras, "size": config.size, "body_model": config.body_model,
            "fit_iters": config.fit_iters,
            "seed": config.seed}


def _claim(config: IngestConfig, calib: Path) -> tuple[Path, Path]:
    """The output folder and its work folder: new, replaced (``--overwrite``) or resumed (``--resume``)."""
    out = Path(config.out)
    work = out / stages.WORK_DIR
    record = work / "config.json"
    wanted = _work_config(config, calib)
    if config.resume:
        if not record.is_file():
            raise FileNotFoundError(f"{out}: no interrupted ingest to resume (no {stages.WORK_DIR}/config.json); "
                                    "run without --resume")
        had = json.loads(record.read_text())
        diff = {k: (had.get(k), v) for k, v in wanted.items() if had.get(k) != (list(v) if isinstance(v, tuple) else v)}
        if diff:
            raise ValueError(f"{record}: the interrupted ingest used other settings {diff} (was, now); "
                             "give the same ones or start again with --overwrite")
        return out, work
    if (out / stages.WORK_DIR).is_dir() and not config.overwrite and not (out / INGEST_MARKER).exists():
        raise FileExistsError(f"{out}: holds an interrupted ingest; pass --resume to continue it or --overwrite "
                              "to start again")
    if config.overwrite and (out / stages.WORK_DIR).is_dir() and not (out / INGEST_MARKER).exists():
        shutil.rmtree(out)  # an interrupted ingest of ours: its work folder marks it
    out = claim_output(out, config.overwrite, INGEST_MARKER, "an ingest")
    work.mkdir(parents=True, exist_ok=True)
    write_text_atomic(record, json.dumps(wanted, indent=2) + "\n")
    return out, work


def ingest(config: IngestConfig) -> IngestResult:
    """Turn ``config.recording`` into the subject ``config.out`` (module docstring); returns what it wrote.

    Raises:
        MissingExtraError: the detector is not installed (before any work).
        RecordingError / ValueError / FileNotFoundError / FileExistsError: bad input, naming the file and what to
            do, before anything is written.
    """
    require_detector()
    root = Path(config.recording)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: recording folder not found")
    calib = Path(config.calibration) if config.calibration else find_calibration(root)
    cameras = _select_cameras(read_cameras(calib), config.cameras, calib)
    streams = match_streams([c.name for c in cameras], find_streams(root))
    frames = check_streams(streams, parse_frame_range(config.frames) if config.frames else None)
    plans = plan_frames(cameras, [(s.width, s.height) for s in streams], [s.path for s in streams], config.size)
    if config.test_cameras >= len(cameras):
        raise ValueError(f"--test-cameras {config.test_cameras}: the recording has {len(cameras)} cameras; at least "
                         "one must stay for training")
    out, work = _claim(config, calib)
    seconds: dict[str, float] = {}
    t = time.perf_counter()
    spec = prepare_body(work, config.body_model)
    seconds["body model"] = time.perf_counter() - t
    t = time.perf_counter()
    for s, plan in zip(streams, plans):
        stages.detect_camera(s, plan, frames, work, config.progress)
    seconds["decode + detect"] = time.perf_counter() - t
    dets = stages.load_detections(work, [s.camera for s in streams])
    cams = [p.camera for p in plans]
    t = time.perf_counter()
    tri = triangulate_stage(work, dets, cams, config)
    seconds["triangulate"] = time.perf_counter() - t
    t = time.perf_counter()
    alphas = stages.refine_masks(dets.masks, tri["points"], tri["valid"], cams)
    seconds["mask refinement"] = time.perf_counter() - t
    t = time.perf_counter()
    fit = fit_stage(work, spec, tri, alphas, cams, list(frames), config)
    seconds["body fit"] = time.perf_counter() - t
    spec = write_fitted_body(out, spec, fit["rest_offsets_mm"])
    report = write_outputs(out, work, config, spec, plans, streams, list(frames), dets, tri, alphas, fit, seconds,
                           calib)
    shutil.rmtree(work)
    return IngestResult(out, report)

