"""The files of a ``deliffas check``: ``report.md``, an overlay PNG per camera and ``summary.json``.

An overlay is the camera's image of its worst-scoring sample, darkened, with the posed template's
silhouette tinted green and the mask's edge drawn in red: a silhouette beside its red outline is a
calibration or pose problem, a silhouette inside a wider outline is clothing the template lacks.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from deliffas.io.infra.reader_checks import write_json_atomic
from deliffas.io.formats.capture_frames import write_image_file
from deliffas.io.infra.text_lines import write_text_atomic
from deliffas.data.check import CheckResult, check_subject
from deliffas.data.check_capture_config import CheckCaptureConfig
from deliffas.data.subjects import parse_subject

__all__ = ["overlay", "write_check_report", "check_summary", "CheckCaptureConfig", "check_capture"]


def overlay(image: np.ndarray, silhouette: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(h, w, 3) uint8: the image at half brightness, silhouette tinted green, mask edge in red."""
    import cv2

    out = image.astype(np.float32) * 0.5
    out[silhouette] = out[silhouette] * 0.5 + np.array([0.0, 160.0, 0.0])
    m8 = mask.astype(np.uint8)
    edge = m8.astype(bool) & ~cv2.erode(m8, np.ones((3, 3), np.uint8)).astype(bool)
    out[edge] = (255.0, 0.0, 0.0)
    return out.clip(0, 255).astype(np.uint8)


def check_summary(result: CheckResult) -> dict:
    """The JSON summary: per camera IoU, the samples, failures, findings and every hypothesis tried."""
    return {
        "ok": result.ok,
        "reason": result.reason,
        "min_iou": result.config.min_iou,
        "offset_mm": result.config.offset_mm,
        "tolerance_px": result.config.tolerance_px,
        "samples": [[s, int(f)] for s, f in result.samples],
        "cameras": [{"index": c, "name": n, "iou": _num(result.camera_iou[c]),
                     "iou_per_sample": [_num(v) for v in result.iou[c]], "failed": c in result.failed}
                    for c, n in enumerate(result.camera_names)],
        "findings": [{"cause": f.cause, "fix": f.fix, "cameras": list(f.cameras), "iou_before": _num(f.iou_before),
                      "iou_after": _num(f.iou_after)} for f in result.findings],
        "hypotheses": {k: _num(v) for k, v in result.hypotheses.items()},
    }


def _num(x: float) -> float | None:
    return None if not np.isfinite(x) else round(float(x), 4)


def write_check_report(result: CheckResult, out_dir: str | os.PathLike) -> Path:
    """Write ``report.md``, ``overlays/<camera>.png`` and ``summary.json`` under ``out_dir``; returns report.md."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lines = ["# deliffas check", "", f"**{'PASS' if result.ok else 'FAIL'}**: {result.reason}", "",
             f"Silhouette: the posed template{f' + {result.config.offset_mm:g} mm shell' if result.config.offset_mm else ''}"
             f", scored by IoU with the mask (pixels within {result.config.tolerance_px} px of the silhouette edge "
             f"not counted), fail below {result.config.min_iou:g}. Samples: "
             + ", ".join(f"{s}:{f}" for s, f in result.samples) + ".", ""]
    if result.findings:
        lines += ["## Likely causes", ""]
        for f in result.findings:
            names = ", ".join(result.camera_names[c] for c in f.cameras)
            undone = f" -> {f.iou_after:.3f} with it undone" if np.isfinite(f.iou_after) else ""
            lines.append(f"- **{f.cause}** (cameras {names}): IoU {f.iou_before:.3f}{undone}. Fix: {f.fix}.")
        lines.append("")
    lines += ["## Cameras", "", "| camera | IoU | status | overlay (green: template, red: mask edge) |",
              "|---|---|---|---|"]
    for c, name in enumerate(result.camera_names):
        png = f"overlays/{c:03d}_{name}.png"
        if c < len(result.views):
            write_image_file(out / png, overlay(*result.views[c]))
        status = "FAIL" if c in result.failed else "ok"
        lines.append(f"| {name} | {result.camera_iou[c]:.3f} | {status} | ![{name}]({png}) |")
    if result.hypotheses:
        lines += ["", "## Hypotheses re-scored", "", "| hypothesis | IoU with it undone |", "|---|---|"]
        lines += [f"| {k} | {v:.3f} |" for k, v in result.hypotheses.items() if np.isfinite(v)]
    write_json_atomic(out / "summary.json", check_summary(result))
    write_text_atomic(out / "report.md", "\n".join(lines) + "\n")
    return out / "report.md"


def check_capture(config: CheckCaptureConfig) -> tuple[CheckResult, Path]:
    """Parse ``config.subject``, :func:`deliffas.data.check.check_subject` it and write the report into
    ``config.out`` (:func:`write_check_report`).

    Returns:
        The result and the path of ``report.md``.
    """
    subject = parse_subject(config.subject, config.format, config.subject_options)
    result = check_subject(subject, config.check)
    return result, write_check_report(result, config.out)
