"""What the ingest of a recording costs, measured where the truth is known: a synthetic capture's videos ingested.

A synthetic capture of the procedural body in SMPL layout is rendered with its videos (``deliffas synth
--videos``); its masks and motion are set aside and ``deliffas ingest`` turns the videos and the calibration
into a subject of its own (masks from the detector, 3-D keypoints, a fitted body per frame). Each ingest
stage is then compared with the truth:

* masks: IoU of the ingested mask against the true one, per camera (median over frames);
* 3-D keypoints: distance to the true body landmarks they stand for (mm; joints, or surface points such as the
  ears and toe tips: :mod:`deliffas.geometry.body_landmarks`);
* body: the fitted surface against the true one per frame (mm): vertex to vertex (same topology) and the
  symmetric nearest-vertex distance;
* avatar: three avatars of the default model, trained on the same cameras and frames and scored on the
  same held-out camera against the TRUE masks: ``truth`` (true masks and body), ``ingested masks`` (true
  body, ingested masks) and ``ingested`` (ingested masks and fitted body, what a recording gives). The
  differences are the PSNR each stage costs. The scores each avatar gets against its own (ingested)
  masks are listed too: they are what a user of a real recording sees.

The held-out camera is the capture's last one, the camera ``ingest`` holds out by default.

Usage: ``python -m recipes.ingest_truth --out OUT [--quick] [--seeds N]``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np

from deliffas.engine.run_sizes import RunSizes
from deliffas.engine.train_config import TrainConfig
from recipes.common import FULL_SUPERSAMPLE, prepare_shards, recipe_parser, seed_list, sized_by_args, \
    train_and_eval, write_outputs
from recipes.seeds import format_stat, train_seeds

FULL = RunSizes(frames=40, test_frames=10, cameras=8, size=256, atlas_res=256, iters=1500, cameras_per_frame=3,
                preset="small", eval_frames=12, supersample=FULL_SUPERSAMPLE)
"""Full mode: 8 cameras (the last held out), 40 frames at 256 x 256 (the detector needs a person of some
100 px or more), the ablations' budget of 1500 iterations."""
QUICK = RunSizes(frames=12, test_frames=2, cameras=4, size=256, atlas_res=32, iters=8, cameras_per_frame=2,
                 preset="tiny", eval_frames=2)
"""Quick mode: the fewest frames an ingest accepts by default (10) and a few more; tiny training."""
FIT_ITERS = {True: 40, False: 300}
"""Body-fit steps of the ingest: quick, full (``ingest``'s default)."""
CONFIGS = ("truth", "ingested masks", "ingested")
VIDEO_FOLDERS = ("img", "fg")
"""A synthetic sequence's video folders: left out of a mask-swapped copy, whose images alone hold its masks."""


# --------------------------------------------------------------------------------------------- capture + ingest
TRUE_BETAS = (0.8, 1.2, -0.6, 0.6, 1.0, -0.5, 0.5, 0.8, 0.7, -0.4)
"""The synthetic person's shape (the procedural body's shape directions: height, girth, arm length, shoulder width,
belly, leg length, head size, hip width, chest depth, torso length; about one unit each): not the mean shape, so
a fit that stays near the mean shape is not rewarded for it."""
BACKGROUND = (0.42, 0.45, 0.5)
"""The synthetic capture's background colour: a mask that spills over it brings it into the training target, as a
real background would (on black, spilled pixels are black like the target's background)."""


def make_capture(out: Path, sizes: RunSizes, jobs: int = 2) -> Path:
    """The synthetic capture (procedural body in SMPL layout shaped by ``TRUE_BETAS``, with videos, on
    ``BACKGROUND``) in ``out/subject``, made once."""
    from deliffas.data.synth import ShadingConfig, SynthConfig, synthesize_capture
    from deliffas.geometry.smpl_motion import procedural_smpl_motion
    from deliffas.io.body_models.amass import write_smpl_motion

    path = out / "subject"
    if not (path / "synth.json").is_file():
        motions = {}
        for name, frames, seed in (("training", sizes.frames, 0), ("test", sizes.test_frames, 1)):
            motions[name] = out / f"motion_{name}.npz"
            write_smpl_motion(motions[name], procedural_smpl_motion(frames, seed, betas=np.asarray(TRUE_BETAS)))
        synthesize_capture(path, SynthConfig(
            num_frames=sizes.frames, num_test_frames=sizes.test_frames, num_cameras=sizes.cameras, width=sizes.size,
            height=sizes.size, test_cameras=(sizes.cameras - 1,), body_model="procedural", videos=True,
            motion=str(motions["training"]), test_motion=str(motions["test"]),
            supersample=sizes.supersample, jobs=jobs, overwrite=True, shading=ShadingConfig(background=BACKGROUND)))
    return path


def run_ingest(subject: Path, out: Path, sizes: RunSizes, quick: bool) -> tuple[Path, float]:
    """``ingest`` of the capture's training videos and calibration into ``out/ingested`` (once); (folder, s)."""
    from deliffas.data.ingest import IngestConfig, ingest

    path = out / "ingested"
    report = path / "ingest_report.json"
    if not report.is_file():
        t0 = time.time()
        ingest(IngestConfig(recording=str(subject / "training" / "img"), out=str(path),
                            calibration=str(subject / "cameras.calibration"), size=(sizes.size, sizes.size),
                            test_frames=0.0, fit_iters=FIT_ITERS[quick], overwrite=True, progress=False))
        (out / "ingest_seconds.json").write_text(json.dumps({"seconds": time.time() - t0}) + "\n")
    return path, float(json.loads((out / "ingest_seconds.json").read_text())["seconds"])


# --------------------------------------------------------------------------------------------- images and masks
def _images(subject: Path):
    """The subject's training images (``ImageFolderSource``: ``read(frame, camera) -> (rgb, alpha)``, ``frames()``)."""
    from deliffas.io.formats.dynacap.frames import ImageFolderSource

    return ImageFolderSource(Path(subject) / "training")


def mask_iou(truth: np.ndarray, mask: np.ndarray) -> float:
    """IoU of two alpha images (foreground = alpha >= 128); 1 when both are empty."""
    a, b = truth >= 128, mask >= 128
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def mask_ious(truth_subject: Path, ingested: Path, num_cameras: int) -> dict:
    """Per camera the median IoU of the ingested masks against the true ones over the ingested frames."""
    truth, got = _images(truth_subject), _images(ingested)
    per_camera = []
    for c in range(num_cameras):
        values = [mask_iou(truth.read(f, c)[1], got.read(f, c)[1]) for f in got.frames()]
        per_camera.append(float(np.median(values)))
    return {"per_camera": per_camera, "median": float(np.median(per_camera))}


def swap_masks(subject: Path, mask_source: Path, out: Path) -> Path:
    """A copy of ``subject`` (links to its files) whose training images carry ``mask_source``'s masks.

    Frames that ``mask_source`` lacks are left out of the copy's images; everything but the training images and
    videos is linked. Made once (``out/.done`` marks a finished copy).
    """
    if (out / ".done").is_file():
        return out
    src, masks = _images(subject), _images(mask_source)
    src_root = src.root
    out.mkdir(parents=True, exist_ok=True)
    for entry in Path(subject).iterdir():
        if entry.name != "training" and not (out / entry.name).exists():
            os.symlink(entry.resolve(), out / entry.name)
    (out / "training").mkdir(exist_ok=True)
    for entry in (Path(subject) / "training").iterdir():
        if entry != src_root and entry.name not in VIDEO_FOLDERS and not (out / "training" / entry.name).exists():
            os.symlink(entry.resolve(), out / "training" / entry.name)
    from deliffas.io.formats.dynacap.frames import write_image

    root = out / "training" / src_root.name
    cameras = len(list(src.path(src.frames()[0], 0).parent.glob("*.png")))
    for f in sorted(set(src.frames()) & set(masks.frames())):
        for c in range(cameras):
            write_image(root, f, c, src.read(f, c)[0], masks.read(f, c)[1])
    (out / ".done").write_text("")
    return out


# --------------------------------------------------------------------------------------------- geometry
def _posed(subject: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The subject's training motion posed: (frames (N,), vertices (N, V, 3) mm, the landmarks of the ingest's
    keypoints (N, J, 3) mm)."""
    import torch

    from deliffas.data.ingest.detect import BODY_LANDMARK_NAMES
    from deliffas.data.subjects.capture_common import SMPL_NUM_BETAS
    from deliffas.geometry.body_landmarks import body_landmarks, posed_template_landmarks
    from deliffas.geometry.templates import build_template, spec_from_file, template_kind

    spec = spec_from_file(next((Path(subject) / "body").glob("*.npz")), num_betas=SMPL_NUM_BETAS)
    kind = template_kind(spec.kind)
    motion = kind.read_motion(Path(subject) / "training" / f"poses{kind.motion_suffix}", spec, None)
    template = build_template(spec, dtype=torch.float32)
    landmarks = body_landmarks(template.v_template, template.J_regressor, template.lbs_weights, BODY_LANDMARK_NAMES)
    with torch.no_grad():
        params = torch.as_tensor(np.asarray(motion.dofs), dtype=torch.float32)
        verts, points = template.pose(params), posed_template_landmarks(template, landmarks, params)
    return np.asarray(motion.frames), verts.numpy().astype(np.float64), points.numpy().astype(np.float64)


def surface_errors(truth: tuple, fitted: tuple) -> dict:
    """The fitted body against the true one over the fitted frames (mm): vertex to vertex and the symmetric
    nearest-vertex distance (means per frame, then the median and max over frames); both as :func:`_posed`."""
    from scipy.spatial import cKDTree

    t_frames, t_verts, _ = truth
    i_frames, i_verts, _ = fitted
    where = {int(f): k for k, f in enumerate(t_frames)}
    v2v, sym = [], []
    for k, f in enumerate(i_frames):
        true, fit = t_verts[where[int(f)]], i_verts[k]
        v2v.append(float(np.linalg.norm(true - fit, axis=1).mean()))
        d_fit = cKDTree(true).query(fit)[0]
        d_true = cKDTree(fit).query(true)[0]
        sym.append(float(0.5 * (d_fit.mean() + d_true.mean())))
    return {"vertex_mm_median": float(np.median(v2v)), "vertex_mm_max": float(np.max(v2v)),
            "surface_mm_median": float(np.median(sym)), "surface_mm_max": float(np.max(sym)), "frames": len(v2v)}


def keypoint_errors(truth: tuple, ingested: Path) -> dict:
    """The triangulated 3-D keypoints (``ingested``'s ``keypoints.npz``) against the true body landmarks they stand
    for (mm; ``truth`` as :func:`_posed`): the median over every triangulated keypoint and per keypoint."""
    from deliffas.data.ingest.detect import KEYPOINT_NAMES
    from deliffas.data.ingest.report import KEYPOINTS_FILE

    with np.load(Path(ingested) / KEYPOINTS_FILE) as kp:
        frames, points, valid = kp["frames"], kp["points3d"], kp["valid3d"]
    t_frames, _, landmarks = truth
    where = {int(f): k for k, f in enumerate(t_frames)}
    rows = [k for k, f in enumerate(frames) if int(f) in where]
    true = landmarks[[where[int(frames[k])] for k in rows]]
    err = np.where(valid[rows], np.linalg.norm(points[rows] - true, axis=2), np.nan)
    per = {name: float(np.nanmedian(err[:, j])) for j, name in enumerate(KEYPOINT_NAMES)}
    return {"median_mm": float(np.nanmedian(err)), "per_keypoint_mm": per}


# --------------------------------------------------------------------------------------------- avatars
def _seed_runner(shards: Path, eval_shards: Path, sizes: RunSizes, device: str):
    """``one_seed`` for ``train_seeds``: train on ``shards``, score on ``eval_shards`` (true masks); the score
    against the training shards' own masks is kept as ``own_masks``."""
    from deliffas.engine.evaluate import EvalConfig, evaluate

    def one(seed: int, run: Path):
        own = train_and_eval(run.parent.name, shards, run, sizes, TrainConfig.model, seed, device)
        if Path(eval_shards) == Path(shards):
            true = own
        else:
            true = evaluate(EvalConfig(run=str(run), split="novel_view", shards=str(eval_shards),
                                       max_frames=sizes.eval_frames, device=device)).to_json()
        true = {**true, "own_masks": own["foreground"]}
        return true, None, None

    return one


def avatars(out: Path, shards: dict[str, Path], eval_shards: dict[str, Path], sizes: RunSizes, seeds: list[int],
            device: str) -> list[dict]:
    """One row per configuration (``CONFIGS``), mean ± std over ``seeds`` against the true masks."""
    rows = []
    for name in CONFIGS:
        row = train_seeds(name, seeds, out / "runs" / name.replace(" ", "_"),
                          _seed_runner(shards[name], eval_shards[name], sizes, device))
        rows.append(row)
    return rows


def _costs(rows: list[dict]) -> dict:
    """Masked PSNR each stage costs (dB, paired by seed, mean): masks, then the body fit, then both."""
    by = {r["name"]: [s["masked_psnr"] for s in r["per_seed"]] for r in rows}

    def loss(a, b):
        return float(np.mean([x - y for x, y in zip(by[a], by[b])]))

    return {"masks_db": loss("truth", "ingested masks"), "body_fit_db": loss("ingested masks", "ingested"),
            "total_db": loss("truth", "ingested")}


# --------------------------------------------------------------------------------------------- recipe
def _notes(masks: dict, keypoints: dict, surface: dict, costs: dict, report: dict, ingest_s: float,
           rows: list[dict], quick: bool) -> list[str]:
    own = {r["name"]: r["own_masks"] for r in rows}
    return [
        "## What each ingest stage costs",
        "",
        "| stage | measured against the truth |",
        "|---|---|",
        f"| masks | IoU median {masks['median']:.3f} (per camera " + " / ".join(f"{v:.3f}" for v in masks["per_camera"])
        + f"); avatar masked PSNR {-costs['masks_db']:+.2f} dB |",
        f"| 3-D keypoints | {keypoints['median_mm']:.1f} mm median from the true body landmarks (reprojection median "
        f"{report['keypoints']['median_px']:.1f} px) |",
        f"| body fit | surface {surface['surface_mm_median']:.1f} mm median (max {surface['surface_mm_max']:.1f}); vertex "
        f"to vertex {surface['vertex_mm_median']:.1f} mm; avatar masked PSNR {-costs['body_fit_db']:+.2f} dB |",
        f"| all | avatar masked PSNR {-costs['total_db']:+.2f} dB against the truth's |",
        "",
        f"Ingest time {ingest_s:.0f} s (" + ", ".join(f"{k} {v:.0f} s" for k, v in report["seconds"].items())
        + "). Scored against their own masks (what a recording's user sees): "
        + ", ".join(f"{k} {v['masked_psnr']:.2f} dB masked" for k, v in own.items()) + ".",
        *(["Quick mode: a few iterations of the tiny preset; the numbers show the pipeline works."] if quick else []),
        ""]


def main(argv=None) -> dict:
    p = recipe_parser(__doc__.splitlines()[0], seeds=True)
    args = p.parse_args(argv)
    sizes = sized_by_args(QUICK if args.quick else FULL, args)
    seeds = seed_list(args)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    truth = Path(args.subject) if args.subject else make_capture(out, sizes, jobs=1 if args.quick else 2)
    ingested, ingest_s = run_ingest(truth, out, sizes, args.quick)
    report = json.loads((ingested / "ingest_report.json").read_text())
    masked = swap_masks(truth, ingested, out / "subject_ingested_masks")
    ingested_true_masks = swap_masks(ingested, truth, out / "ingested_true_masks")
    jobs = 1 if args.quick else 2
    shards = {name: prepare_shards(out, subject, sizes, name=f"shards_{name.replace(' ', '_')}", jobs=jobs,
                                   check=False)
              for name, subject in (("truth", truth), ("ingested masks", masked), ("ingested", ingested))}
    eval_shards = {"truth": shards["truth"], "ingested masks": shards["truth"],
                   "ingested": prepare_shards(out, ingested_true_masks, sizes, name="shards_ingested_true_masks",
                                              jobs=jobs, check=False)}
    masks = mask_ious(truth, ingested, sizes.cameras)
    true_body = _posed(truth)
    keypoints = keypoint_errors(true_body, ingested)
    surface = surface_errors(true_body, _posed(ingested))
    rows = avatars(out, shards, eval_shards, sizes, seeds, args.device)
    costs = _costs(rows)
    title = "Ingest against the truth: masks, keypoints, body fit and the avatar" + (" — quick mode" if args.quick else "")
    notes = _notes(masks, keypoints, surface, costs, report, ingest_s, rows, args.quick)
    extra = {"quick": args.quick, "sizes": dataclasses.asdict(sizes), "seeds": seeds, "masks": masks,
             "keypoints": keypoints, "surface": surface, "psnr_cost": costs, "ingest_seconds": ingest_s,
             "ingest_report": report, "subject": str(truth),
             "masked_psnr": {r["name"]: format_stat(r["stats"]["masked_psnr"]) for r in rows}}
    return write_outputs(out, title, rows, extra, notes, chart=False)


if __name__ == "__main__":
    main()
