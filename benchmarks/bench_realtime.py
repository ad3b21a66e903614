"""Real-time rendering on CPU: the fast path's frame against its irreducible work, and frames per second by preset.

Scene: the benchmark capture (``_capture.py``), frame 0, camera 0 rescaled to 940 x 1285 (and 256^2,
512^2). Models: ``two_surface`` at the ``realtime``, ``small`` and ``paper`` presets, and ``REFLECTED``
(``two_surface_reflect_texture``, the view direction reflected about the normal) at ``realtime``, untrained
(seed 0; its texture atlases random), atlas side = the shards' (256), U-Nets on their inference forward. One
torch thread (``BENCH_THREADS``) on both sides of every ratio.

* frame, pose held: ``fast.frame.fast_render_camera`` with the frame's U-Net features cached
  (the viewer while the pose holds), in the dtype ``RenderPathConfig()`` resolves to (bf16 where the CPU
  has native bf16); for ``two_surface`` and for ``REFLECTED``, each against its own irreducible work.
* irreducible work, measured in the same run: one plain z-buffer pass of the outer surface
  (``UVRasterizer.depth_pass``, incl. projecting its vertices), one ``torch.mm`` per MLP layer shape
  into preallocated outputs in the same dtype (no bias, activation or concatenation), and one
  ``index_select`` of every sampled feature value (nearest texel) from the two maps (and the normal map
  where the model reflects the view direction).
  The frame's fp32 pass takes the first layer's encoded part from per-coordinate tables
  (``RenderPathConfig.pe_table``, on by default), so it does fewer multiply-adds than the GEMM chain counts
  and the ratio can read below 1.
* encoding table: the frame with the tables against the frame with the exact encoding
  (``RenderPathConfig(pe_table=False)``), same run; no target.
* frames in flight: a stream of 8 frames one after the other (1 and 2 intra-op threads) against
  ``render_stream`` with two frames in flight on one thread each, for ``two_surface`` at ``realtime``, the default
  of ``deliffas train``, and ``REFLECTED`` at ``realtime`` with its U-Nets at half the atlas side and 32 feature
  channels (:data:`HALF_SIDE_32`); no target.
* reflected direction: ``REFLECTED``'s frame against ``two_surface_texture``'s (the same model without the
  direction), pose held and U-Nets per frame, interleaved; no target.
* fps: 1000 / frame ms, with the U-Nets run per frame (``deliffas render``: the pose changes every
  frame) and with them cached (pose held); no target, machines vary.

Smoke mode: the smoke bench capture, 64x96 for 940x1285 and 32^2 for 256^2 and 512^2, 2 frames per stream.
"""

from __future__ import annotations

import dataclasses
import time

import torch

from benchmarks._capture import bench_capture
from benchmarks._timing import BENCH_THREADS, best_times, torch_threads
from benchmarks.common import Result, sized

RATIO_TARGET = 1.3
SIZES = {"256^2": (256, 256), "512^2": (512, 512), "940x1285": (1285, 940)}
"""Frame sizes, name: (width, height); the last one is the ratio, stream and reflection rows' size."""
SMOKE_SIZES = {"32^2": (32, 32), "64x96": (96, 64)}


def _sizes() -> dict[str, tuple[int, int]]:
    """:data:`SIZES`, or :data:`SMOKE_SIZES` in smoke mode."""
    return sized(SIZES, SMOKE_SIZES)


def _frame_camera(sample) -> tuple[str, object]:
    """The name of the last of :func:`_sizes` and the sample's first camera rescaled to it."""
    name, size = list(_sizes().items())[-1]
    return name, sample.cameras[0].rescaled(*size)


HALF_SIDE_32 = {"unet_downsample": 2, "feature_channels": 32, "unet": {"out_channels": 32}}
"""Model overrides of the stream row at ``realtime`` with U-Nets at half the atlas side and 32 feature channels
(docs/results.md, "Speed against accuracy at 940 x 1285": within 0.3 dB of the default)."""


def _model(info, preset: str, name: str = "two_surface", overrides: dict | None = None):
    """The zoo's model ``name`` at ``preset`` with ``overrides`` (``TrainConfig.model_overrides``), untrained (seed 0;
    texture atlases, if any, random)."""
    from deliffas.engine.train import TrainConfig, resolve_model_config
    from deliffas.models.deliffas import DeliffasModel
    from deliffas.models.unet import optimize_for_inference

    train = TrainConfig(shards="", out="", model=name, preset=preset, model_overrides=dict(overrides or {}))
    cfg = resolve_model_config(train, info["atlas_res"], 2)
    torch.manual_seed(0)
    model = DeliffasModel(cfg).eval()
    with torch.no_grad():
        for texture in model.texture_parameters():
            texture.uniform_(0, 1)
    return optimize_for_inference(model)


def _gemm_chain(model, n: int, dtype: torch.dtype):
    """``torch.mm`` per layer shape of the model's MLP on n rows, preallocated, in ``dtype``."""
    mlp = model.mlp
    shapes = [(lin.in_features, lin.out_features) for lin in [*mlp.hidden, mlp.output]]
    xs = {k: torch.rand(n, k).to(dtype) for k, _ in shapes}
    ws = [torch.rand(k, m).to(dtype) for k, m in shapes]
    outs = [torch.empty(n, m, dtype=dtype) for _, m in shapes]

    def run():
        for (k, _), w, out in zip(shapes, ws, outs):
            torch.mm(xs[k], w, out=out)
    return run


def _gather(features, n: int):
    """One ``index_select`` of n texels' channels from each of the two maps and the normal map, if any (nearest texel)."""
    sampled = [m for m in (features.outer, features.inner, features.normals) if m is not None]
    maps = [m.permute(0, 2, 3, 1).reshape(-1, m.shape[1]) for m in sampled]
    idx = torch.randint(0, maps[0].shape[0], (n,), generator=torch.Generator().manual_seed(0))

    def run():
        for m in maps:
            torch.index_select(m, 0, idx)
    return run


def _frame_fns(model, sample, info, camera, fast):
    from deliffas.engine.shading import render_camera
    from deliffas.engine.timing import StageTimer
    from deliffas.geometry.raycast import UVRaycaster

    device = torch.device("cpu")
    rc = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
    with torch.no_grad():
        features = model.encode(*sample.normal_maps(device))

    def held(timer=None):  # pose held: features cached, the frame's surfaces already set up
        with torch.no_grad():
            return render_camera(model, features, rc, camera, device, timer or StageTimer(device),
                                 render_path=fast)

    once = dataclasses.replace(fast, project_features=False)

    def full():  # a new pose: surfaces and U-Nets per frame, features shaded once (as engine.render does)
        with torch.no_grad():
            rc2 = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
            feats = model.encode(*sample.normal_maps(device))
            return render_camera(model, feats, rc2, camera, device, StageTimer(device), render_path=once)
    return held, full, features, rc


def _ratio_rows(sample, info, name: str = "two_surface") -> list[Result]:
    """The frame of model ``name`` (realtime preset) against its irreducible work (PASS/FAIL), its fps and the
    encoding table's gain; rows named as ever for ``two_surface``, after the model otherwise."""
    from deliffas.fast.uv_sources import device_camera_rays
    from deliffas.fast.rasterize import frame_rasterizer
    from deliffas.fast.config import RenderPathConfig
    from deliffas.fast.shade import mlp_dtype
    from deliffas.engine.timing import StageTimer

    fast = RenderPathConfig()
    dtype = mlp_dtype(fast.dtype)
    model = _model(info, "realtime", name)
    size, cam = _frame_camera(sample)
    label = f"{size} realtime preset" + ("" if name == "two_surface" else f" ({name})")
    held, _full, features, rc = _frame_fns(model, sample, info, cam, fast)
    n = device_camera_rays(rc, cam, "cpu", "raster").num_rays
    rz = frame_rasterizer(rc)
    gemm, gather = _gemm_chain(model, n, dtype), _gather(features, n)
    exact, _, _, _ = _frame_fns(model, sample, info, cam, dataclasses.replace(fast, pe_table=False))
    t = best_times({"frame": held, "raster": lambda: rz.depth_pass(cam), "gemm": gemm, "gather": gather,
                    "exact": exact}, repeat=5, min_time=3.0)
    timer = StageTimer(torch.device("cpu"))
    held(timer)
    irreducible = t["raster"] + t["gemm"] + t["gather"]
    ratio = t["frame"] / irreducible
    dname = str(dtype).replace("torch.", "")
    return [
        Result("realtime", f"{label}, pose held ({n} rays, {dname}): frame / irreducible",
               t["frame"] * 1000, "ms", baseline="raster pass + GEMM chain + gather", ratio=ratio,
               target=f"<= {RATIO_TARGET}", passed=ratio <= RATIO_TARGET,
               note=f"raster {t['raster'] * 1000:.1f} ms, GEMMs {t['gemm'] * 1000:.1f} ms, gather "
                    f"{t['gather'] * 1000:.1f} ms; stages of one frame: "
                    + ", ".join(f"{k} {v:.1f}" for k, v in timer.total_ms.items())),
        Result("realtime", f"{label}, pose held: fps", 1 / t["frame"], "fps",
               note=f"{BENCH_THREADS} torch thread; no target (machines vary)"),
        Result("realtime", f"{label}, pose held: frame with the encoding table", t["frame"] * 1000,
               "ms", baseline="exact encoding (pe_table=False)", ratio=t["frame"] / t["exact"],
               note=f"exact {t['exact'] * 1000:.1f} ms; the table applies to the fp32 pass only ({dname} here); "
                    "no target"),
    ]


def _reflect_rows(sample, info) -> list[Result]:
    """``REFLECTED``'s realtime frame against ``two_surface_texture``'s (no view direction), interleaved: pose held
    and U-Nets per frame."""
    from deliffas.fast.config import RenderPathConfig
    from deliffas.models.zoo import REFLECTED, TEXTURED

    size, cam = _frame_camera(sample)
    fns = {}
    for name in (TEXTURED, REFLECTED):
        held, full, _, _ = _frame_fns(_model(info, "realtime", name), sample, info, cam, RenderPathConfig())
        fns[f"{name} held"], fns[f"{name} full"] = held, full
    t = best_times(fns, repeat=5, min_time=3.0)
    rows = []
    for kind, label in (("held", "pose held"), ("full", "U-Nets per frame")):
        ref, got = t[f"{TEXTURED} {kind}"], t[f"{REFLECTED} {kind}"]
        rows.append(Result("realtime", f"{size} realtime preset, {label}: {REFLECTED} fps", 1 / got, "fps",
                           baseline=f"{TEXTURED}, same frame", ratio=ref / got,
                           note=f"{TEXTURED} {1 / ref:.1f} fps; {BENCH_THREADS} torch thread; no target"))
    return rows


def _stream_rows(sample, info, name: str = "two_surface", preset: str = "realtime",
                 overrides: tuple[str, dict] | None = None) -> list[Result]:
    """Frames per second of a stream of 940x1285 frames of ``name`` at ``preset`` (with ``overrides``: its label and
    model overrides): one after the other on 1 and on 2 intra-op threads, and two frames in flight (``render_stream``,
    one thread each), interleaved; pose held and per frame."""
    from deliffas.fast.frame import render_stream
    from deliffas.fast.config import RenderPathConfig

    model = _model(info, preset, name, overrides[1] if overrides else None)
    if overrides:
        what = f"{name} ({preset}, {overrides[0]})"
    else:
        what = f"{preset} preset" if name == "two_surface" else f"{name} ({preset}, the default of deliffas train)"
    size, cam = _frame_camera(sample)
    held, full, _, _ = _frame_fns(model, sample, info, cam, RenderPathConfig())
    frames = sized(8, 2)

    def sequential(fn, threads):
        def run():
            with torch_threads(threads):
                for _ in range(frames):
                    fn()
        return run

    def in_flight(fn):
        def run():
            for _ in render_stream(lambda _i: fn(), range(frames), 2):
                pass
        return run

    rows = []
    for label, fn in (("pose held", held), ("U-Nets per frame", full)):
        t = best_times({"seq1": sequential(fn, 1), "seq2": sequential(fn, 2), "flight2": in_flight(fn)}, repeat=2,
                       max_rounds=3)
        fps = {k: frames / v for k, v in t.items()}
        rows.append(Result("realtime", f"{size} {what}, {label}: fps, 2 frames in flight",
                           fps["flight2"], "fps", baseline="1 frame at a time, 2 intra-op threads",
                           ratio=fps["flight2"] / fps["seq2"],
                           note=f"1 frame at a time: {fps['seq1']:.1f} fps on 1 thread, {fps['seq2']:.1f} on 2; "
                                f"{frames} frames per round; no target (machines vary)"))
    return rows


def _fps_rows(sample, info) -> list[Result]:
    from deliffas.fast.config import RenderPathConfig

    rows = []
    sizes = _sizes()
    for preset in ("realtime", "small", "paper"):
        model = _model(info, preset)
        for size, (w, h) in sizes.items():
            cam = sample.cameras[0].rescaled(w, h)
            fast_held, fast_full, _, _ = _frame_fns(model, sample, info, cam, RenderPathConfig())
            plain_held, _, _, _ = _frame_fns(model, sample, info, cam, RenderPathConfig(path="plain"))
            fns = {"fast_held": fast_held, "fast_full": fast_full}
            if preset == "small" and size == list(sizes)[-1]:
                fns["plain_held"] = plain_held
            t = best_times(fns, repeat=2, max_rounds=2)
            note = f"U-Nets per frame {1 / t['fast_full']:.1f} fps ({t['fast_full'] * 1000:.0f} ms)"
            ratio = None
            if "plain_held" in t:
                ratio = t["plain_held"] / t["fast_held"]
                note += f"; plain path (ray cast, fp32) {t['plain_held'] * 1000:.0f} ms"
            rows.append(Result("realtime", f"{preset} {size}: fps, pose held (fast path)", 1 / t["fast_held"], "fps",
                               baseline="plain path, pose held" if ratio else "", ratio=ratio, note=note))
    return rows


def run() -> list[Result]:
    subject, shards, _ = bench_capture()
    from benchmarks.bench_engine import _sample
    from deliffas.engine.train_config import TrainConfig
    from deliffas.models.zoo import REFLECTED

    sample, info = _sample(shards)
    sample = dataclasses.replace(sample, cameras=sample.cameras[:1], images=sample.images[:1], masks=sample.masks[:1])
    t0 = time.perf_counter()
    with torch_threads():
        rows = (_ratio_rows(sample, info) + _ratio_rows(sample, info, REFLECTED) + _reflect_rows(sample, info)
                + _stream_rows(sample, info) + _stream_rows(sample, info, TrainConfig.model, TrainConfig.preset)
                + _stream_rows(sample, info, REFLECTED, "realtime", ("U-Nets at S / 2, 32 features", HALF_SIDE_32))
                + _fps_rows(sample, info))
    rows[-1].note += f" (group took {time.perf_counter() - t0:.0f} s)"
    return rows
