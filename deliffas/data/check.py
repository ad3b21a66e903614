"""``deliffas check``: does a parsed capture's posed template land on its masks, camera by camera?

For a sample of frames and every camera, the template is posed (``build_template(subject.template)``),
moved out to its outer shell (``geometry.shell.offset_shell``, d = ``CheckConfig.offset_mm``: the
masks show clothes and hair the template lacks), ray cast at a reduced resolution and compared with
the mask by IoU. When cameras fail, the classic mistakes are re-scored as hypotheses (the camera
pose inverted, R transposed, OpenGL axes, translations in m vs mm, poses offset by a few frames,
cameras in another order); a hypothesis that lifts the IoU past the threshold is named as the likely
cause with its fix. The report (markdown, overlays, JSON) is written by :mod:`deliffas.data.check_report`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch

from deliffas.io.cameras import Camera
from deliffas.io.motion import Motion
from deliffas.geometry.raycast import build_scene, first_hits
from deliffas.geometry.shell import offset_shell
from deliffas.geometry.templates import build_template, template_kind
from deliffas.data.check_config import CheckConfig
from deliffas.data.subjects import Subject, SubjectSequence

__all__ = ["CheckConfig", "Finding", "CheckResult", "SubjectCheckError", "check_subject", "check_before_convert",
           "silhouettes", "mask_iou", "scaled_camera", "scaled_view", "posed_surface"]

log = logging.getLogger(__name__)

OFFSET_GAIN = 0.05
"""A pose/image frame offset is reported when it lifts the mean IoU (over the scored pairs) by this much."""

OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Flips camera y and z: an OpenGL camera pose read as OpenCV's (or back)."""


class SubjectCheckError(ValueError):
    """A capture whose posed template misses its masks; the message is the report's one-line reason."""


@dataclass(frozen=True)
class Finding:
    """One named likely cause."""
    cause: str
    """Short name of the mistake (``camera-to-world``, ``frame offset +2``, ...)."""
    fix: str
    """What to change."""
    cameras: tuple[int, ...]
    """The cameras it concerns (calibration indices)."""
    iou_before: float
    """Mean IoU of those cameras as parsed."""
    iou_after: float
    """Mean IoU of those cameras with the hypothesis applied."""


@dataclass(frozen=True)
class CheckResult:
    """The scores of one check.

    Attributes:
        camera_names: (C,) names by calibration index.
        samples: the (sequence, frame) pairs scored.
        iou: (C, S) float64 IoU per camera and sample (NaN: empty mask and silhouette).
        camera_iou: (C,) mean IoU per camera.
        failed: calibration indices below ``min_iou`` or flagged as outliers.
        findings: likely causes, best first.
        hypotheses: every hypothesis tried -> mean IoU over the cameras it touches.
        config: the configuration used.
        views: per camera (image (h, w, 3) uint8, silhouette (h, w) bool, mask (h, w) bool) of its worst sample.
    """

    camera_names: tuple[str, ...]
    samples: tuple[tuple[str, int], ...]
    iou: np.ndarray
    camera_iou: np.ndarray
    failed: tuple[int, ...]
    findings: tuple[Finding, ...]
    hypotheses: dict
    config: CheckConfig
    views: tuple = ()

    @property
    def ok(self) -> bool:
        return not self.failed

    @property
    def reason(self) -> str:
        """One line: which cameras fail and the likely cause."""
        if self.ok:
            return f"all {len(self.camera_names)} cameras pass (IoU >= {self.config.min_iou:g}, min " \
                   f"{np.nanmin(self.camera_iou):.3f})"
        worst = ", ".join(f"{self.camera_names[c]} {self.camera_iou[c]:.2f}" for c in self.failed[:6])
        line = f"{len(self.failed)} of {len(self.camera_names)} cameras fail the silhouette check (IoU {worst})"
        if self.findings:
            f = self.findings[0]
            change = f" -> {f.iou_after:.2f}" if np.isfinite(f.iou_after) else ""
            line += f"; likely cause: {f.cause} (IoU {f.iou_before:.2f}{change}); fix: {f.fix}"
        return line


# --------------------------------------------------------------------------------------------- scoring
def mask_iou(sil: np.ndarray, mask: np.ndarray, tolerance_px: int = 0) -> float:
    """IoU of two (H, W) bool images, ignoring pixels within ``tolerance_px`` of ``sil``'s edge (NaN if both empty)."""
    if tolerance_px > 0:
        import cv2

        k = np.ones((2 * tolerance_px + 1,) * 2, np.uint8)
        s8 = sil.astype(np.uint8)
        band = cv2.dilate(s8, k).astype(bool) & ~cv2.erode(s8, k).astype(bool)
        keep = ~band
        sil, mask = sil & keep, mask & keep
    union = np.count_nonzero(sil | mask)
    return float(np.count_nonzero(sil & mask) / union) if union else float("nan")


def scaled_camera(camera: Camera, max_side: int) -> Camera:
    """``camera`` rescaled so that its longer image side is at most ``max_side`` pixels."""
    s = min(1.0, max_side / max(camera.width, camera.height))
    w, h = max(1, round(camera.width * s)), max(1, round(camera.height * s))
    return camera.rescaled(w, h) if (w, h) != (camera.width, camera.height) else camera


def scaled_view(rgb: np.ndarray, mask: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """A frame's (H, W, 3) uint8 image and (H, W) uint8 mask at ``camera``'s size: (h, w, 3) uint8, (h, w) bool."""
    import cv2

    size = (camera.width, camera.height)
    return (cv2.resize(rgb, size, interpolation=cv2.INTER_AREA),
            cv2.resize(mask, size, interpolation=cv2.INTER_AREA) >= 128)


def silhouettes(verts: np.ndarray, faces: np.ndarray, cameras: list[Camera]) -> list[np.ndarray]:
    """(H, W) bool silhouette of one mesh (V, 3) mm in each camera (a ray through each pixel centre hits it)."""
    scene = build_scene(verts, faces)
    out = []
    for cam in cameras:
        o, d = cam.rays()
        t, _, _ = first_hits(scene, o, d)
        out.append(np.isfinite(t).reshape(cam.height, cam.width))
    return out


class _Scorer:
    """Posed surfaces and downscaled masks of the sampled frames, scored against any set of cameras."""

    def __init__(self, subject: Subject, config: CheckConfig):
        self.subject, self.config = subject, config
        self.template = build_template(subject.template, dtype=torch.float64)
        self.faces = self.template.faces.numpy()
        self.samples: list[tuple[str, int]] = []
        self.masks: list[list[np.ndarray]] = []  # [sample][camera] (h, w) bool
        self.images: list[list[np.ndarray]] = []  # [sample][camera] (h, w, 3) uint8, for the overlays
        cams = [scaled_camera(c, config.max_side) for c in subject.cameras]
        for name, seq in subject.sequences.items():
            if seq.poses is None:
                log.info("check: sequence %s has no pose parameters (tracked meshes); not checked", name)
                continue
            frames = _sample(seq, config.frames)
            src = seq.images.open()
            try:
                for f in frames:
                    row_m, row_i = [], []
                    for c, cam in enumerate(cams):
                        rgb, m = scaled_view(*src.read(int(f), c), cam)
                        row_m.append(m)
                        row_i.append(rgb)
                    self.samples.append((name, int(f)))
                    self.masks.append(row_m)
                    self.images.append(row_i)
            finally:
                src.close()
        if not self.samples:
            raise ValueError(f"{subject.root}: no sequence with pose parameters to check")
        self.cameras = cams

    def surface(self, seq: SubjectSequence, frame: int, motion: Motion | None = None) -> np.ndarray | None:
        return posed_surface(self.template, motion if motion is not None else seq.poses, frame, self.config.offset_mm)

    def score(self, cameras: list[Camera] | None = None, motions: dict[str, Motion] | None = None,
              frame_shift: int = 0, which: list[int] | None = None, order: list[int] | None = None) -> np.ndarray:
        """(C, S) IoU of the cameras ``which`` (others NaN); ``order[c]`` = the calibration scored against mask c."""
        cams = cameras if cameras is not None else self.cameras
        which = list(range(len(cams))) if which is None else which
        order = order if order is not None else list(range(len(cams)))
        out = np.full((len(cams), len(self.samples)), np.nan)
        for s, (name, f) in enumerate(self.samples):
            seq = self.subject.sequences[name]
            verts = self.surface(seq, f + frame_shift, (motions or {}).get(name))
            if verts is None:
                continue
            sils = silhouettes(verts, self.faces, [cams[order[c]] for c in which])
            for k, c in enumerate(which):
                if sils[k].shape != self.masks[s][c].shape:
                    continue
                out[c, s] = mask_iou(sils[k], self.masks[s][c], self.config.tolerance_px)
        return out


def posed_surface(template, motion: Motion, frame: int, offset_mm: float = 0.0) -> np.ndarray | None:
    """(V, 3) mm: ``template`` posed by ``motion``'s row of capture frame ``frame`` (None: no such row), moved
    out to its outer shell by ``offset_mm`` when non-zero (the surface the check scores)."""
    rows = np.nonzero(motion.frames == frame)[0]
    if len(rows) == 0:
        return None
    with torch.no_grad():
        verts = template.pose(torch.as_tensor(motion.dofs[rows[:1]])).numpy()[0]
    faces = template.faces.numpy()
    return offset_shell(verts, faces, offset_mm) if offset_mm else verts


def _sample(seq: SubjectSequence, n: int) -> np.ndarray:
    frames = np.asarray(seq.poses.frames if seq.poses is not None else seq.frames)
    frames = np.intersect1d(frames, seq.frames)
    if len(frames) <= n:
        return frames
    return frames[np.unique(np.linspace(0, len(frames) - 1, n).round().astype(int))]


def _mean(x: np.ndarray) -> np.ndarray:
    with np.errstate(all="ignore"):
        counts = np.sum(np.isfinite(x), axis=-1)
        return np.where(counts > 0, np.nansum(np.nan_to_num(x, nan=0.0), axis=-1) / np.maximum(counts, 1), np.nan)


# --------------------------------------------------------------------------------------------- hypotheses
def _with_pose(cam: Camera, E: np.ndarray) -> Camera:
    return replace(cam, world_to_cam=E)


def _transposed(cam: Camera) -> Camera:
    E = cam.world_to_cam.copy()
    E[:3, :3] = E[:3, :3].T
    return _with_pose(cam, E)


def _scaled_t(factor: float) -> Callable[[Camera], Camera]:
    def f(cam: Camera) -> Camera:
        E = cam.world_to_cam.copy()
        E[:3, 3] *= factor
        return _with_pose(cam, E)
    return f


CAMERA_HYPOTHESES: dict[str, tuple[Callable[[Camera], Camera], str]] = {
    "camera-to-world pose read as world-to-camera": (
        lambda c: _with_pose(c, np.linalg.inv(c.world_to_cam)),
        "invert the extrinsics (the file stores camera -> world; deliffas wants world -> camera)"),
    "transposed rotation": (
        _transposed, "transpose R (a column-major matrix read row-major, or R of the inverse pose)"),
    "OpenGL camera axes": (
        lambda c: _with_pose(c, OPENGL_FROM_OPENCV @ c.world_to_cam),
        "flip the camera's y and z axes (OpenGL/Blender/nerfstudio -> OpenCV: diag(1, -1, -1))"),
    "camera translation in metres read as mm": (
        _scaled_t(1000.0), "multiply the camera translations by 1000 (the file is in metres)"),
    "camera translation in mm read as metres": (
        _scaled_t(0.001), "divide the camera translations by 1000 (the file is in millimetres)"),
}


def _smpl_transl(motions: dict[str, Motion], factor: float) -> dict[str, Motion]:
    out = {}
    for k, m in motions.items():
        d = m.dofs.copy()
        d[:, :3] *= factor
        out[k] = Motion(m.frames, d)
    return out


def _try_global(sc: _Scorer, base: np.ndarray, failed: list[int], tried: dict) -> list[Finding]:
    """Hypotheses that change every camera, or the poses, scored on the failing cameras."""
    cfg = sc.config
    before = float(np.nanmean(base[failed]))
    found = []

    def consider(cause: str, fix: str, iou: np.ndarray, cams: list[int]) -> None:
        after = float(np.nanmean(iou[cams])) if np.isfinite(iou[cams]).any() else float("nan")
        tried[cause] = after
        if np.isfinite(after) and after >= cfg.min_iou and after > before + 0.1:
            found.append(Finding(cause, fix, tuple(cams), float(np.nanmean(base[cams])), after))

    for cause, (fn, fix) in CAMERA_HYPOTHESES.items():
        cams = [fn(c) if i in failed else c for i, c in enumerate(sc.cameras)]
        consider(cause, fix, sc.score(cams, which=failed), failed)
    motions = {k: s.poses for k, s in sc.subject.sequences.items() if s.poses is not None}
    if template_kind(sc.subject.template.kind).smpl_params:
        for factor, cause, fix in ((0.001, "SMPL translation in mm read as metres",
                                    "divide the SMPL translations by 1000 (the smpl template takes metres)"),
                                   (1000.0, "SMPL translation in metres read as mm",
                                    "multiply the SMPL translations by 1000")):
            consider(cause, fix, sc.score(motions=_smpl_transl(motions, factor), which=failed), failed)
    return found


def _try_offsets(sc: _Scorer, base: np.ndarray, tried: dict) -> list[Finding]:
    """Poses of frame f + k against the images of frame f, on every camera (tried even when all cameras pass:
    a small offset lowers the IoU without failing it)."""
    cfg = sc.config
    cams = list(range(len(sc.cameras)))
    best = None
    for k in [s * d for d in range(1, cfg.frame_offsets + 1) for s in (1, -1)]:
        iou = sc.score(frame_shift=k)
        both = np.isfinite(iou) & np.isfinite(base)
        if not both.any():
            continue
        before, after = float(base[both].mean()), float(iou[both].mean())
        tried[f"frame offset {k:+d} between images and poses"] = after
        if after >= cfg.min_iou and after - before >= OFFSET_GAIN and (best is None or after > best.iou_after):
            best = Finding(f"frame offset {k:+d} between images and poses",
                           f"the image of frame f shows the pose of frame f{k:+d}: shift the pose (or image) "
                           f"numbering by {k}", tuple(cams), before, after)
    return [best] if best is not None else []


def _try_order(sc: _Scorer, base: np.ndarray, failed: list[int], tried: dict) -> list[Finding]:
    """Each failing camera's mask against every camera's calibration: a better match elsewhere = wrong order."""
    C = len(sc.cameras)
    if len(failed) < 2:
        return []
    cross = np.full((C, C), np.nan)  # cross[mask c, calibration j]
    for j in range(C):
        order = [j] * C
        cross[:, j] = _mean(sc.score(order=order, which=failed))
    best = {c: int(np.nanargmax(cross[c])) for c in failed if np.isfinite(cross[c]).any()}
    moved = [c for c, j in best.items() if j != c and cross[c, j] >= sc.config.min_iou]
    after = float(np.nanmean([cross[c, best[c]] for c in moved])) if moved else float("nan")
    tried["wrong camera order"] = after
    if len(moved) >= 2:
        pairs = ", ".join(f"{sc.subject.camera_names[c]}<-{sc.subject.camera_names[best[c]]}" for c in moved[:6])
        return [Finding("wrong camera order", f"images and calibration list cameras in different orders ({pairs}): "
                        "match image folders to calibration names", tuple(moved),
                        float(np.nanmean(base[moved])), after)]
    return []


MASK_FULL = 0.99
"""A mask with at least this fraction of foreground pixels in every sampled frame is all foreground."""


def _unusable_masks(sc: _Scorer) -> dict[str, list[int]]:
    """``empty`` / ``all foreground`` -> the cameras whose every sampled mask is so (a missing mask reads as all
    foreground)."""
    out: dict[str, list[int]] = {}
    for c in range(len(sc.cameras)):
        cover = [float(sc.masks[s][c].mean()) for s in range(len(sc.samples))]
        if max(cover) == 0.0:
            out.setdefault("empty", []).append(c)
        elif min(cover) >= MASK_FULL:
            out.setdefault("all foreground", []).append(c)
    return out


def _mask_findings(unusable: dict[str, list[int]], cam_iou: np.ndarray) -> list[Finding]:
    fix = ("give the capture its foreground masks (EasyMocap mask/<cam>/<frame>.png, ZJU-MoCap mask/ or "
           "mask_cihp/, DynaCap: RGBA images, fg videos or convert --masks SUBDIR); without them the IoU cannot judge "
           "the calibration")
    causes = {"empty": "masks empty (no foreground pixel)",
              "all foreground": "masks missing or all foreground (every pixel is the subject)"}
    return [Finding(causes[kind], fix, tuple(cams), float(np.nanmean(cam_iou[cams])), float("nan"))
            for kind, cams in unusable.items()]


def check_subject(subject: Subject, config: CheckConfig = CheckConfig()) -> CheckResult:
    """Score the posed template's silhouette against the masks per camera; name likely causes of failures."""
    sc = _Scorer(subject, config)
    iou = sc.score()
    cam_iou = _mean(iou)
    C = len(sc.cameras)
    failed = [c for c in range(C) if not cam_iou[c] >= config.min_iou]
    for c in range(C):
        others = np.delete(cam_iou, c)
        if c not in failed and C > 2 and np.isfinite(others).any() and cam_iou[c] < np.nanmedian(others) - config.outlier_gap:
            failed.append(c)
    tried: dict = {}
    unusable = _unusable_masks(sc)
    findings = _mask_findings(unusable, cam_iou) if unusable else _try_offsets(sc, iou, tried)
    if unusable:  # no hypothesis is scored against masks that cannot tell a silhouette from the background
        failed = sorted(set(failed) | {c for cams in unusable.values() for c in cams})
    elif findings:
        failed = sorted(set(failed) | set(findings[0].cameras))
    elif failed:
        failed.sort()
        findings = _try_global(sc, iou, failed, tried) + _try_order(sc, iou, failed, tried)
        findings.sort(key=lambda f: f.iou_after, reverse=True)
        passing = [c for c in range(C) if c not in failed]
        if not findings and passing and len(failed) <= max(1, C // 4):
            ref = float(np.nanmedian(cam_iou[passing]))
            findings.append(Finding("a camera far below the others",
                                    "check this camera's calibration entry and masks, or leave it out (--cameras)",
                                    tuple(failed), float(np.nanmean(cam_iou[failed])), ref))
    log.info("check %s: camera IoU %s", subject.root, np.round(cam_iou, 3).tolist())
    return CheckResult(subject.camera_names, tuple(sc.samples), iou, cam_iou, tuple(failed), tuple(findings), tried,
                       config, _views(sc, iou))


def check_before_convert(subject: Subject, frames: int = 2) -> CheckResult | None:
    """The check ``convert`` runs first (on ``frames`` frames); None when no sequence has pose parameters.

    Raises:
        SubjectCheckError: a camera fails; the message is the one-line reason.
    """
    if all(s.poses is None for s in subject.sequences.values()):
        log.info("check: %s has tracked meshes only; the silhouette check is skipped", subject.root)
        return None
    result = check_subject(subject, CheckConfig(frames=frames))
    if not result.ok:
        raise SubjectCheckError(f"{subject.root}: {result.reason} (details: deliffas check {subject.root} --out "
                                "REPORT; convert anyway with --no-check)")
    return result


def _views(sc: _Scorer, iou: np.ndarray) -> tuple:
    """Per camera the image, silhouette and mask of its worst-scoring sample."""
    out = []
    for c in range(len(sc.cameras)):
        row = np.where(np.isfinite(iou[c]), iou[c], np.inf)
        s = int(np.argmin(row))
        name, f = sc.samples[s]
        verts = sc.surface(sc.subject.sequences[name], f)
        sil = silhouettes(verts, sc.faces, [sc.cameras[c]])[0]
        out.append((sc.images[s][c], sil, sc.masks[s][c]))
    return tuple(out)
