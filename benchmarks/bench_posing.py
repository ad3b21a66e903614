"""Posing throughput: frames/s of the batched DQS and LBS skinning of a whole motion (smoke mode: its first 16
frames)."""

from __future__ import annotations

import torch

from benchmarks.common import SAMPLE_DIR, Result, best_time, sized


def run() -> list[Result]:
    from deliffas.io.formats.dynacap.character import read_character, read_motion
    from deliffas.geometry.templates import DDCTemplate

    if not (SAMPLE_DIR / "ddc.character").is_file():
        return [Result("posing", "skipped: ../shared/dynacap-sample absent", 0.0, "")]
    character = read_character(SAMPLE_DIR / "ddc.character")
    motion = read_motion(SAMPLE_DIR / "skeletoolToGTPose" / "poseAngles.motion", character.skeleton.num_dofs)
    x = torch.tensor(motion.dofs, dtype=torch.float32)
    x = x[: sized(len(x), 16)]
    results = []
    template = DDCTemplate(character)
    n = x.shape[0]
    with torch.no_grad():
        t_fk = best_time(lambda: template.fk(x), repeat=2)
        times = {mode: best_time(lambda m=mode: template.pose(x, m), repeat=2) for mode in ("dqs", "lbs")}
    results.append(Result("posing", f"FK only, {n} frames, 173 joints", n / t_fk, "frames/s"))
    for mode, t in times.items():
        results.append(Result("posing", f"{mode.upper()} pose, {n} frames x 5514 verts", n / t, "frames/s",
                              baseline="LBS", ratio=times["lbs"] / t, note="ratio = LBS time / this time"))
    return results
