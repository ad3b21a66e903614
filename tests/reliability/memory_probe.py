"""Peak-memory probe, run in a fresh subprocess by test_resource_bounds.py (not a test module).

``python memory_probe.py '{"shards": DIR, "render": [W, H, ZOOM, [CHUNK, ...]], "train": [S, W, H, ZOOM,
[CHUNK, ...]]}'`` prints JSON: per phase the growth of the peak resident set (VmHWM after
``/proc/self/clear_refs`` reset it) over the resident set before the phase, in bytes.

render: one camera of the first frame of DIR at W x H (focal length x ZOOM, so the subject fills
the frame), the paper model's MLP and U-Net widths at S = 256: ray casting alone, encode alone,
the shading stage alone per chunk (``all`` = one chunk), and ``render_frame`` with the first chunk.

train: ``train_step`` (Adam, paper widths, atlas S) on such a frame per ray chunk (``all`` =
unchunked), after a warm-up step so Adam's state is part of the baseline; and one U-Net's
forward + backward alone.

glibc is told (``MALLOC_MMAP_THRESHOLD_``, set by the caller) to serve every large block by mmap,
so freed memory leaves the resident set and each phase starts from a clean baseline.
"""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
import torch

from deliffas.engine.memory import frame_features_bytes
from deliffas.engine.memory import peak_rss_growth as measure
from deliffas.models.ray_query import RayQuery
from deliffas.models.unet import optimize_for_inference


def _paper_model(S: int):
    from deliffas.engine.train import TrainConfig, resolve_model_config
    from deliffas.models import DeliffasModel

    cfg = resolve_model_config(TrainConfig(shards="-", out="-", preset="paper"), S, 2)
    torch.manual_seed(0)
    return DeliffasModel(cfg)


def render(shards: str, width: int, height: int, zoom: float, chunks: list[str]) -> dict:
    """``render_frame`` of one camera at W x H with chunk ``chunks[0]``; the shading stage alone per chunk."""
    from deliffas.engine.shading import render_frame
    from deliffas.engine.rays import camera_rays
    from deliffas.engine.timing import StageTimer
    from deliffas.geometry.raycast import UVRaycaster

    S = 256
    torch.set_num_threads(1)
    model = optimize_for_inference(_paper_model(S).eval())  # as evaluate/render (load_run) run it
    frame, info = _frame(shards, width, height, zoom, S, model.config.input_channels)
    cam = frame.cameras[0]
    raycaster = UVRaycaster(frame.inner_verts, info["faces"], frame.outer_verts, info["atlas"])
    cpu = torch.device("cpu")
    small = dataclasses.replace(frame, cameras=[cam.rescaled(48, 64)])
    render_frame(model, small, raycaster, cpu, StageTimer(cpu), chunk_size=1024)  # warm-up: lazy inits
    out: dict = {"pixels": width * height, "atlas_res": S, "rays": frame.rays[0].num_rays,
                 "param_bytes": sum(p.numel() * p.element_size() for p in model.parameters())}
    out["cast"], _ = measure(lambda: camera_rays(raycaster, cam))
    ni = torch.from_numpy(frame.normal_inner)[None]
    with torch.no_grad():
        out["encode"], features = measure(lambda: model.encode(ni, ni))
        out["features_bytes"] = frame_features_bytes(features)
        rays = frame.rays[0]
        query = RayQuery(torch.zeros(rays.num_rays, dtype=torch.long), torch.from_numpy(rays.uv_inner),
                         torch.from_numpy(rays.uv_outer), viewdir=torch.from_numpy(rays.viewdir),
                         inner_from_outer=torch.from_numpy(rays.inner_from_outer))
        out["shade"] = {}
        for chunk in chunks:  # the shading stage alone: chunk-bounded activations + (N, 3) output
            c = rays.num_rays if chunk == "all" else int(chunk)
            out["shade"][chunk], _ = measure(lambda: model.shade_chunked(features, query, chunk_size=c))
    del features
    chunk = int(chunks[0])
    out["render_chunk"] = chunk
    out["render"], images = measure(lambda: render_frame(model, frame, raycaster, cpu, StageTimer(cpu),
                                                         chunk_size=chunk))
    assert torch.isfinite(images).all() and images.any()
    return out


def _frame(shards: str, width: int, height: int, zoom: float, S: int, channels: int):
    """First frame of SHARDS seen by one camera at W x H (focal x zoom) with random S x S normal maps."""
    from deliffas.engine.data_bridge import evaluation_samples
    from deliffas.engine.rays import frame_rays

    samples, info = evaluation_samples(shards, "all", max_frames=1, protocol="all")
    sample = next(iter(samples))
    cam = sample.cameras[0].rescaled(width, height)
    K = cam.K.copy()
    K[0, 0] *= zoom  # zoom in about the principal point: the subject fills more of the frame
    K[1, 1] *= zoom
    cam = dataclasses.replace(cam, K=K)
    normals = (torch.rand(channels, S, S, generator=torch.Generator().manual_seed(0)) * 2 - 1).numpy()
    rays = frame_rays(sample.inner_verts, sample.outer_verts, info["faces"], info["atlas"], [cam])
    rng = np.random.default_rng(0)
    frame = dataclasses.replace(sample, cameras=[cam], camera_ids=sample.camera_ids[:1], normal_inner=normals,
                                normal_outer=normals, rays=rays,
                                images=rng.random((1, height, width, 3), dtype=np.float32),
                                masks=(rng.random((1, height, width)) > 0.5).astype(np.float32))
    return frame, info


def train(shards: str, S: int, width: int, height: int, zoom: float, chunks: list[str]) -> dict:
    from deliffas.engine.train import train_step

    torch.set_num_threads(1)
    model = _paper_model(S).train()
    frame, _ = _frame(shards, width, height, zoom, S, model.config.input_channels)
    out: dict = {"atlas_res": S, "pixels": width * height, "rays": frame.rays[0].num_rays,
                 "param_bytes": sum(p.numel() * p.element_size() for p in model.parameters()),
                 "unet_param_bytes": sum(p.numel() * p.element_size() for p in model.unet_inner.parameters())}
    opt = torch.optim.Adam(model.parameters(), lr=1e-6)
    cpu = torch.device("cpu")
    train_step(model, frame, opt, cpu, ray_chunk=1024)  # warm-up: Adam state exists from here on
    x = torch.from_numpy(frame.normal_inner)[None]

    def unet_step():
        model.unet_inner(x).square().mean().backward()
        model.zero_grad(set_to_none=True)

    out["unet_fwd_bwd"], _ = measure(unet_step)
    out["train_step"] = {}
    for chunk in chunks:
        c = None if chunk == "all" else int(chunk)
        out["train_step"][chunk], res = measure(lambda: train_step(model, frame, opt, cpu, ray_chunk=c, mlp_block=None))
        assert np.isfinite(res["loss"])
        opt.zero_grad(set_to_none=True)
    return out


if __name__ == "__main__":
    spec = json.loads(sys.argv[1])
    result = {}
    if "render" in spec:
        result["render"] = render(spec["shards"], *spec["render"])
    if "train" in spec:
        result["train"] = train(spec["shards"], *spec["train"])
    print(json.dumps(result))
