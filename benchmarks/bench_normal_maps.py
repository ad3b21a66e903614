"""Temporal normal maps: one precomputed gather per frame against re-rasterising and a plain gather.

For the template's atlas at S = 256, 512, 1024: ``NormalMapGather.apply`` of one frame's vertex
normals (its default method: the fused C kernel when it builds, else the sparse product), the
texel table built once beforehand, against

* naive (ratio >= 20): ``rasterize_normal_map_naive``, which re-rasterises the atlas into a texel
  table for every frame (what a renderer drawing the map in UV space each frame pays);
* memory-bound floor (ratio <= 2): ``torch.index_select`` of 3 S^2 float32 values (one per output
  value, indices = the texels' first vertex x 3 + channel) from the (V x 3) normals into a fresh
  output of the same size as the map: the bytes the map writes and one read per written value.

Also reported: the one-off build of the fused kernel (C compiler run + load, once per process),
the sparse-product fallback (``method="sparse"``) against the same index_select, and maps per
second of batched frames (8 frames per call). Smoke mode: S = 32, 64.
"""

from __future__ import annotations

import torch

from benchmarks import _avatar
from benchmarks._timing import best_times
from benchmarks.common import Result, sized

GROUP = "normals"
NAIVE_TARGET = 20.0
GATHER_TARGET = 2.0
SIZES = (256, 512, 1024)
SMOKE_SIZES = (32, 64)


def run() -> list[Result]:
    return _avatar.avatar_run(GROUP, _run)


def _run(av: _avatar.Avatar) -> list[Result]:
    from deliffas.geometry.atlas import uv_texel_table
    from deliffas.geometry.normal_maps import NormalMapGather, fused_kernel_status, rasterize_normal_map_naive

    normals = av.normals_seq  # (K, V, 3) float32
    frames, num_verts = normals.shape[0], normals.shape[1]
    faces = torch.from_numpy(av.faces)
    status = fused_kernel_status()  # builds the kernel here if no earlier module of this process did
    method = "fused" if status.available else "sparse (fused kernel unavailable)"
    results = [Result(
        GROUP, "fused kernel build (C compiler + load, once per process)", status.build_seconds, "s",
        note=(f"{status.command}; AVX2 path: {'yes' if status.avx2 else 'no'}" if status.available
              else f"unavailable: {status.reason}"),
    )]  # fmt: skip
    for size in sized(SIZES, SMOKE_SIZES):
        gather = NormalMapGather.from_table(uv_texel_table(av.atlas, size), faces)
        state = {"k": 0}

        def one_frame():
            state["k"] = (state["k"] + 1) % frames
            return gather.apply(normals[state["k"]])

        src = normals[0].reshape(-1).contiguous()  # (V * 3,)
        idx = (gather.vert_index[:, :1] * 3 + torch.arange(3)).reshape(-1).contiguous()  # (3 S^2,)

        t = best_times({"apply": one_frame, "index_select": lambda: torch.index_select(src, 0, idx),
                        "sparse": lambda: gather.apply(normals[state["k"]], method="sparse"),
                        "batch": lambda: gather.apply(normals)}, repeat=5, min_time=3.0, max_rounds=60)
        t_naive = best_times({"naive": lambda: rasterize_normal_map_naive(normals[:1], faces, av.atlas, size)},
                             repeat=3)["naive"]
        fast = gather.apply(normals[0])
        diff_naive = float((rasterize_normal_map_naive(normals[:1], faces, av.atlas, size)[0] - fast).abs().max())
        diff_sparse = float((gather.apply(normals[0], method="sparse") - fast).abs().max())
        speedup = t_naive / t["apply"]
        over_gather = t["apply"] / t["index_select"]
        results.append(Result(
            GROUP, f"S={size}: apply, 1 frame, {num_verts} verts", 1.0 / t["apply"], "maps/s",
            baseline="rasterize_normal_map_naive per frame", ratio=speedup, target=f">= {NAIVE_TARGET:.0f}",
            passed=speedup >= NAIVE_TARGET,
            note=(f"{method}: apply {t['apply'] * 1e3:.2f} ms, naive {t_naive * 1e3:.0f} ms; max |diff| vs naive "
                  f"{diff_naive:.1e}, vs sparse {diff_sparse:.1e}"),
        ))  # fmt: skip
        results.append(Result(
            GROUP, f"S={size}: apply vs index_select of 3 S^2 floats", t["apply"] * 1e3, "ms",
            baseline="torch.index_select, same output size", ratio=over_gather, target=f"<= {GATHER_TARGET:.0f}",
            passed=over_gather <= GATHER_TARGET, note=f"{method}; index_select {t['index_select'] * 1e3:.2f} ms",
        ))  # fmt: skip
        results.append(Result(
            GROUP, f"S={size}: sparse fallback vs index_select", t["sparse"] * 1e3, "ms",
            baseline="torch.index_select, same output size", ratio=t["sparse"] / t["index_select"],
            note='apply(method="sparse"): without a C compiler, or off CPU',
        ))  # fmt: skip
        results.append(Result(GROUP, f"S={size}: apply, {frames} frames per call", frames / t["batch"], "maps/s"))
    return results
