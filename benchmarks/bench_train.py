"""Training speed: a training step against its irreducible work, and iterations per second at 128^2 and 256^2.

The step is the default run's (``deliffas train`` without options: its model, K = 3 cameras of one
frame, U-Nets once per frame, at most ``rays_per_step`` of the shaded rays, L1 plus the saturation penalty on
the U-Nets' logits, Adam), timed as ``engine.train_step`` runs it, with the rays already cast; at 256^2 also the
step on every shaded ray.

Irreducible work, counted from the shapes of this very step:

* the U-Nets: FLOPs of every (transposed) convolution in one forward (``bench_unet.conv_flops``),
  times 3 for forward + backward (the backward computes the input and the weight gradients, each as
  many multiply-adds as the forward), less once the first layer's (its input, the normal maps, needs no
  gradient), at the convolution rate measured in this run (one 3x3 conv
  64 -> 64 at 256^2, forward, timed in the same interleaved rounds as the step);
* the light-field MLP: 2 x multiply-adds per ray (``LightFieldMLP.flops_per_ray``) x rays, times 3,
  at the GEMM rate measured in this run (a (rays x 64) @ (64 x 64) product, in the same rounds).

Sampling, encoding, the loss, the saturation penalty and the optimizer are counted as zero: the ratio step /
irreducible is what the U-Nets and MLP would cost at the machine's dense rates, and the target is <= 2.
Smoke mode: 32^2 and 64^2 on the smoke bench capture, the ratio at the larger.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import nn

from benchmarks._capture import bench_capture
from benchmarks._timing import BENCH_THREADS, best_times, torch_threads
from benchmarks.bench_unet import conv_flops
from benchmarks.common import Result, sized

GROUP = "train"
TARGET = 2.0
K = 3


def _sample(size: int):
    """One frame of the bench capture seen by K cameras, images and rays at ``size``^2, normal maps at ``size``."""
    import numpy as np
    import torch.nn.functional as F

    from deliffas.engine.data_bridge import evaluation_samples
    from deliffas.engine.rays import camera_rays
    from deliffas.geometry.raycast import UVRaycaster

    _, shards, _ = bench_capture()
    samples, info = evaluation_samples(str(shards), "all", max_frames=1, protocol="all", temporal_window=2)
    s = next(samples)
    cams = [c if c.width == size else c.rescaled(size, size) for c in s.cameras[:K]]
    raycaster = UVRaycaster(s.inner_verts, info["faces"], s.outer_verts, info["atlas"])

    def resize(a: np.ndarray, channels_last: bool) -> np.ndarray:
        t = torch.from_numpy(np.ascontiguousarray(a))
        t = t.permute(0, 3, 1, 2) if channels_last else t
        if t.shape[-1] != size:
            t = F.interpolate(t, size=(size, size), mode="area")
        return (t.permute(0, 2, 3, 1) if channels_last else t).contiguous().numpy()

    images = resize(s.images[:K], True)
    masks = resize(s.masks[:K, None], False)[:, 0]
    normals = [resize(m[None], False)[0] for m in (s.normal_inner, s.normal_outer)]
    return dataclasses.replace(s, images=images, masks=masks, cameras=cams, camera_ids=s.camera_ids[:K],
                               rays=[camera_rays(raycaster, c) for c in cams], normal_inner=normals[0],
                               normal_outer=normals[1])


def _model(size: int):
    """The default run's model at atlas side ``size`` and its optimizer, as ``deliffas train`` makes them."""
    from deliffas.engine.train import make_optimizer
    from deliffas.engine.train_config import TrainConfig, resolve_model_config
    from deliffas.models.deliffas import DeliffasModel

    torch.manual_seed(0)
    cfg = TrainConfig(shards="", out="")
    model = DeliffasModel(resolve_model_config(cfg, size, 2))
    return model, make_optimizer(model, cfg)


def _irreducible_s(model, sample, conv_rate: float, gemm_rate: float) -> tuple[float, float, float]:
    """(seconds, U-Net FLOPs, MLP FLOPs) of forward + backward at the measured rates."""
    ni = torch.from_numpy(sample.normal_inner)[None]
    nets = [n for n in (*model.inner_unets(), model.unet_outer) if n is not None]
    # the first layer's input (the normal maps) needs no gradient: its backward is the weight gradient alone
    unet = sum(3 * conv_flops(n, ni) - conv_flops(n.down[0][0], ni) for n in nets)
    rays = sum(r.num_rays for r in sample.rays)
    mlp = 3 * model.mlp.flops_per_ray() * rays
    return unet / conv_rate + mlp / gemm_rate, unet, mlp


def _timed_with_rates(step, rays: int) -> tuple[float, float, float]:
    """(step seconds, conv FLOP/s, GEMM FLOP/s): the best times of ``step``, a 3x3 conv 64 -> 64 at 256^2 and a
    (rays x 64) @ (64 x 64) GEMM, interleaved in the same rounds, so that a change of the machine's speed during
    the run (a shared host's clock or its neighbours) moves the step and its floor together."""
    gen = torch.Generator().manual_seed(0)
    conv = nn.Conv2d(64, 64, 3, padding=1, bias=False)
    xc = torch.rand(1, 64, 256, 256, generator=gen)
    a, b = torch.rand(rays, 64, generator=gen), torch.rand(64, 64, generator=gen)

    def rate(fn):
        def run():
            with torch.inference_mode():
                fn()
        return run

    t = best_times({"step": step, "conv": rate(lambda: conv(xc)), "gemm": rate(lambda: a @ b)}, repeat=5,
                   min_time=4.0, max_rounds=20)
    return t["step"], 2 * 256 * 256 * 64 * 64 * 9 / t["conv"], 2 * rays * 64 * 64 / t["gemm"]


def run() -> list[Result]:
    with torch_threads():
        return _run()


def _run() -> list[Result]:
    import numpy as np

    from deliffas.engine.samples import subsample_rays
    from deliffas.engine.train_config import RAYS_PER_STEP, TrainConfig
    from deliffas.engine.train_step import train_step
    from deliffas.models.losses import SaturationTerm

    defaults = TrainConfig(shards="", out="")
    saturation = SaturationTerm(defaults.saturation_weight, defaults.saturation_margin)  # as the trainer's

    rows = []
    sizes = sized((128, 256), (32, 64))
    for size in sizes:
        every_ray = _sample(size)
        shaded = sum(r.num_rays for r in every_ray.rays)
        default = subsample_rays(every_ray, RAYS_PER_STEP, np.random.default_rng(0))
        cases = [("default run's step", default)]
        if default is not every_ray:  # at 128^2 the default step shades every ray
            cases.append(("every shaded ray", every_ray))
        for label, sample in cases:
            model, opt = _model(size)
            step = lambda: train_step(model, sample, opt, torch.device("cpu"), saturation=saturation)  # noqa: E731
            rays = sum(r.num_rays for r in sample.rays)
            if size == sizes[-1]:
                t_step, conv_rate, gemm_rate = _timed_with_rates(step, rays)
            else:
                t_step = best_times({"step": step}, repeat=4, min_time=3.0, max_rounds=12)["step"]
            rows.append(Result(GROUP, f"{label}, {size}^2, K={K} ({rays} of {shaded} rays)", 1 / t_step, "it/s",
                               note=f"{t_step * 1e3:.0f} ms per step, rays cast beforehand; {BENCH_THREADS} torch "
                                    "thread"))
            if size == sizes[-1]:
                rows.append(_ratio_row(label, size, model, sample, t_step, conv_rate, gemm_rate))
    return rows


def _ratio_row(label: str, size: int, model, sample, t_step: float, conv_rate: float, gemm_rate: float) -> Result:
    """The step against its irreducible work at the rates measured with it (PASS/FAIL against :data:`TARGET`)."""
    floor, unet, mlp = _irreducible_s(model, sample, conv_rate, gemm_rate)
    ratio = t_step / floor
    return Result(GROUP, f"step / irreducible work, {size}^2, K={K}, {label}", ratio, "x",
                  baseline="U-Net + MLP forward and backward FLOPs at the measured conv / GEMM rates", ratio=ratio,
                  target=f"<= {TARGET:.1f}", passed=ratio <= TARGET,
                  note=f"U-Nets {unet / 1e9:.2f} GFLOP at {conv_rate / 1e9:.0f} GFLOP/s, MLP {mlp / 1e9:.2f} GFLOP at "
                       f"{gemm_rate / 1e9:.0f} GFLOP/s: {floor * 1e3:.0f} ms against {t_step * 1e3:.0f} ms")
