"""Peak memory of rendering one 940 x 1285 frame, run in a fresh process by bench_engine.

``python -m benchmarks._frame_memory SHARDS CHUNK`` prints JSON: the growth of the peak resident
set of ``render_frame`` (paper preset widths at the capture's atlas side, one camera of the first
frame rescaled to 1285 x 940) with ``CHUNK`` rays per chunk and with every ray in one chunk, and
the stated bound ``deliffas.engine.memory.render_peak_bound`` for the chunked call. Smoke mode
(``benchmarks.common.SMOKE_ENV``): a 96 x 64 frame.
"""

from __future__ import annotations

import dataclasses
import json
import sys

import torch

from benchmarks.common import sized

WIDTH, HEIGHT = 1285, 940


def main(shards: str, chunk: int) -> dict:
    from deliffas.engine.data_bridge import evaluation_samples
    from deliffas.engine.shading import render_frame
    from deliffas.engine.memory import frame_features_bytes, peak_rss_growth, render_peak_bound
    from deliffas.engine.rays import camera_rays
    from deliffas.engine.timing import StageTimer
    from deliffas.engine.train import TrainConfig, resolve_model_config
    from deliffas.geometry.raycast import UVRaycaster
    from deliffas.models import DeliffasModel, optimize_for_inference

    torch.set_num_threads(1)
    samples, info = evaluation_samples(shards, "all", max_frames=1, protocol="all")
    sample = next(iter(samples))
    width, height = sized((WIDTH, HEIGHT), (96, 64))
    cam = sample.cameras[0].rescaled(width, height)
    frame = dataclasses.replace(sample, cameras=[cam], camera_ids=sample.camera_ids[:1])
    torch.manual_seed(0)
    model = DeliffasModel(resolve_model_config(TrainConfig(shards="-", out="-", preset="paper"), info["atlas_res"],
                                               info["temporal_window"])).eval()
    optimize_for_inference(model)  # as evaluate/render (load_run) run it
    raycaster = UVRaycaster(frame.inner_verts, info["faces"], frame.outer_verts, info["atlas"])
    cpu = torch.device("cpu")
    small = dataclasses.replace(frame, cameras=[cam.rescaled(48, 64)])
    render_frame(model, small, raycaster, cpu, StageTimer(cpu), chunk_size=1024)  # warm-up: lazy inits
    rays = camera_rays(raycaster, cam).num_rays
    with torch.no_grad():
        features_bytes = frame_features_bytes(model.encode(*frame.normal_maps(cpu)))
    out = {"width": width, "height": height, "pixels": width * height, "rays": rays, "chunk": chunk,
           "atlas_res": model.config.atlas_res, "features_bytes": features_bytes,
           "bound": render_peak_bound(features_bytes, width * height, chunk, rays)}
    for name, size in (("chunked", chunk), ("unchunked", rays)):
        out[name], images = peak_rss_growth(lambda: render_frame(model, frame, raycaster, cpu, StageTimer(cpu),
                                                                 chunk_size=size))
        assert torch.isfinite(images).all()
    return out


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], int(sys.argv[2]))))
