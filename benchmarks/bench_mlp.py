"""MLP stage: achieved FLOP/s of the light-field MLP against plain matmuls of the same shapes.

Model: ``two_surface`` at the ``paper`` preset (8 x 256, features after layer 4; inputs 84 + 64).
Inputs: the MLP inputs of every foreground ray of the benchmark camera (``gather_inputs`` on
uniform random feature maps standing in for the U-Net output), at 256^2 and 940 x 1285.

Baseline, same run, same dtype: the chain of ``torch.mm`` calls with the MLP's weight shapes
(84->256, 256->256 x 4, 320->256, 256->256 x 2, 256->3) on the same number of rows, bias-free,
no activation, no concatenation, into preallocated outputs: the pure GEMM cost of the MLP.
Both are credited the same FLOPs (2 per multiply-add), so the ratio is t_matmul / t_mlp.
Target: >= 0.70 for fp32 and for bf16.

bf16 runs on a copy of the MLP cast to bfloat16 with bfloat16 inputs. This CPU has AVX2 but no
native bf16 arithmetic, so bf16 is timed on at most ``BF16_RAYS`` rays. Its quality change is the
RGB difference to the fp32 MLP on the same inputs (max, mean, PSNR). Smoke mode: the smoke sizes and atlas of
``_avatar``.
"""

from __future__ import annotations

import copy
import math

import torch

from benchmarks import _avatar
from benchmarks._timing import best_times
from benchmarks.common import Result

GROUP = "mlp"
TARGET = 0.70
BF16_RAYS = 8192
"""bf16 is timed on at most this many rays (it runs several times slower than fp32 here)."""
REPEATS = (5, 2)
"""Timed rounds at the smaller and at the larger image size."""


def matmul_chain(mlp: torch.nn.Module, num_rows: int, dtype: torch.dtype):
    """A function running one ``torch.mm`` per MLP layer shape into preallocated outputs."""
    gen = torch.Generator().manual_seed(1)
    layers = [*mlp.hidden, mlp.output]
    xs = [torch.rand(num_rows, layer.in_features, generator=gen).to(dtype) for layer in layers]
    ws = [layer.weight.detach().to(dtype) for layer in layers]
    outs = [torch.empty(num_rows, layer.out_features, dtype=dtype) for layer in layers]

    def run() -> None:
        for x, w, out in zip(xs, ws, outs):
            torch.mm(x, w.t(), out=out)

    return run


def mac_flops(mlp: torch.nn.Module) -> int:
    """2 x multiply-adds of one MLP evaluation (biases and activations not counted)."""
    return 2 * sum(layer.in_features * layer.out_features for layer in [*mlp.hidden, mlp.output])


def run() -> list[Result]:
    return _avatar.avatar_run(GROUP, _run)


def _run(av: _avatar.Avatar) -> list[Result]:
    model = _avatar.paper_model()
    features = _avatar.random_features(model)
    mlp32 = model.mlp
    mlp16 = copy.deepcopy(model.mlp).to(torch.bfloat16)
    flops = mac_flops(mlp32)
    results = []
    for size, repeat in zip(_avatar.sizes(), REPEATS):
        r = _avatar.rays(size)
        with torch.inference_mode():
            enc, feats = model.gather_inputs(features, _avatar.ray_query(r))
            n = enc.shape[0]
            t = best_times({"mlp": lambda: mlp32(enc, feats), "mm": matmul_chain(mlp32, n, torch.float32)},
                           repeat=repeat, min_time=3.0, max_rounds=40)
            nb = min(n, BF16_RAYS)
            enc_b, feats_b = enc[:nb].bfloat16(), feats[:nb].bfloat16()
            tb = best_times({"mlp": lambda: mlp16(enc_b, feats_b), "mm": matmul_chain(mlp32, nb, torch.bfloat16)},
                            repeat=2)
            rgb32 = mlp32(enc[:nb], feats[:nb])
            rgb16 = mlp16(enc_b, feats_b).float()
        diff = (rgb16 - rgb32).abs()
        mse = float((diff**2).mean())
        psnr = 10 * math.log10(1.0 / mse) if mse > 0 else math.inf
        for dtype, tt, rows in (("fp32", t, n), ("bf16", tb, nb)):
            ratio = tt["mm"] / tt["mlp"]
            results.append(Result(
                GROUP, f"{size} {dtype} MLP 8x256, {rows} rays", flops * rows / tt["mlp"] / 1e9, "GFLOP/s",
                baseline=f"{dtype} torch.mm chain, same shapes, bias-free", ratio=ratio, target=f">= {TARGET:.2f}",
                passed=ratio >= TARGET,
                note=(f"MLP {tt['mlp'] * 1e3:.1f} ms, matmuls {tt['mm'] * 1e3:.1f} ms "
                      f"({flops * rows / tt['mm'] / 1e9:.1f} GFLOP/s); {av.source}; 2 FLOPs per MAC for both"),
            ))  # fmt: skip
        results.append(Result(GROUP, f"{size} bf16 time / fp32 time, {nb} rays", (tb["mlp"] / nb) / (t["mlp"] / n), "x"))
        results.append(Result(GROUP, f"{size} bf16 vs fp32 RGB: max abs diff", float(diff.max()), "RGB [0,1]",
                              note=f"mean abs {float(diff.mean()):.2e}; untrained (Glorot) weights"))
        results.append(Result(GROUP, f"{size} bf16 vs fp32 RGB: PSNR", psnr, "dB",
                              note=f"mean abs diff {float(diff.mean()):.2e}"))
    return results
