"""A camera's image by the CPU fast path, and frames rendered several at once (:func:`render_stream`).

A camera's image is rendered here as the engine's plain path (``engine.shading.render_camera``) renders it,
stage by stage (``uv``, ``sample``, ``mlp``), with three replacements:

* ``uv``: the source ``RenderPathConfig.uv`` names, as on the plain path (``deliffas.fast.uv_sources``; ``auto`` =
  the C rasteriser, :class:`~deliffas.fast.rasterize.UVRasterizer`, where its kernel builds: the ray caster's
  shaded pixels and uvs; the ray caster is used where a vertex is behind the camera);
* ``sample``: :class:`~deliffas.fast.shade.FastShader` writes the encodings and sampled
  features straight into the MLP's operands (one C pass);
* ``mlp``: the MLP as a chain of ``addmm`` in fp32, or in bf16 where the CPU has native bf16;
* by default ``sample`` and ``mlp`` are one C pass instead (``FastShader.shade_fused``: a tile of rays in
  the vector lanes, the hidden layers in bf16 with native bf16 dot products where the dtype is bf16, else fp32,
  the first layer's encoded part from per-coordinate tables in fp32 (``RenderPathConfig.pe_table``), the feature
  layer's feature part sampled from maps projected once per frame's features
  (``RenderPathConfig.project_features``); every colour written to its pixel), timed as the ``mlp`` stage.

:class:`~deliffas.fast.config.RenderPathConfig` is the switch (``path="fast"`` or ``"plain"``, the uv source, the
fast path's knobs). ``deliffas render`` and ``deliffas view`` take the fast path on CPU devices by default
(:func:`path_for_device`: other devices render plain); ``deliffas eval`` keeps the plain path, whose numbers are
the reference.

:func:`render_stream` keeps several frames in flight: each frame renders in a worker thread on one torch
intra-op thread (every stage releases the GIL: oneDNN, the C kernels through ctypes, open3d), so consecutive
frames overlap on the cores and come out in order, identical to the sequential path (``in_flight=1``).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, ContextManager, Iterable, Iterator, Protocol, TypeVar, runtime_checkable

import torch

from deliffas.fast.config import RenderPathConfig
from deliffas.fast.shade import FastShader, mlp_dtype, supports
from deliffas.fast.uv_sources import RASTER_MAX_PIXELS_ON_GPU, device_camera_rays, uv_source
from deliffas.geometry.camera_rays import CameraRays
from deliffas.geometry.raycast import UVRaycaster
from deliffas.io.cameras import Camera
from deliffas.models.deliffas import DeliffasModel, FrameFeatures
from deliffas.models.ray_query import RayBatch, paint_images, ray_query

__all__ = ["StageTiming", "RenderPath", "path_for_device", "describe_render_path", "fast_render_camera",
           "render_stream"]

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")


@runtime_checkable
class StageTiming(Protocol):
    """What the fast path times its stages with (the engine's ``engine.timing.StageTimer`` is one)."""

    def stage(self, name: str) -> ContextManager[None]:
        """A context that adds its wall-clock time to stage ``name``."""
        ...


def path_for_device(cfg: RenderPathConfig, device: torch.device | str) -> RenderPathConfig:
    """``cfg`` where ``device`` is a CPU (the fast path's only device), else ``cfg`` on the plain path."""
    return cfg if not cfg.fast or torch.device(device).type == "cpu" else dataclasses.replace(cfg, path="plain")


@dataclass(frozen=True)
class RenderPath:
    """The path ``render_images`` takes for a model (:func:`describe_render_path`)."""

    line: str
    """One line naming the path and, where it is not the one asked for, why."""
    fallback: bool
    """True where the fast path was asked for and a slower one is taken (a variant it does not shade, or its C
    kernel did not build): ``render`` and ``view`` warn instead of only logging at ``-v``."""


_UVS = {"raster": "rasterised uvs", "raycast": "ray-cast uvs", "torch": "uvs by the torch rasteriser"}


def _uvs(requested: str, device: torch.device) -> str:
    """The uv source's words, ``auto`` resolved as for an image of any size."""
    small, large = uv_source(device, requested), uv_source(device, requested, RASTER_MAX_PIXELS_ON_GPU + 1)
    return _UVS[small] if small == large else f"{_UVS[small]} (above 2^19 pixels an image: {_UVS[large]})"


def describe_render_path(model: DeliffasModel, cfg: RenderPathConfig, device: torch.device | str) -> RenderPath:
    """The path ``render_images`` takes for ``model`` on ``device`` with ``cfg`` (``deliffas render -v`` and
    ``deliffas view -v`` print its line)."""
    dev = torch.device(device)
    uvs = _uvs(cfg.uv, dev)
    if not cfg.fast or dev.type != "cpu":
        why = "--render-path plain" if not cfg.fast else f"device {dev} (the fast path is the CPU's)"
        return RenderPath(f"plain path ({why}): {uvs}, model.shade in chunks", False)
    fast = cfg
    frames = f"{fast.frames_in_flight()} frame(s) in flight"
    if not supports(model):
        return RenderPath(f"fast path, {uvs}, {frames}; variant {model.spec.name} is not one FastShader shades, so "
                          "its own gather_inputs and MLP shade the rays", True)
    shader = _shader(model, mlp_dtype(fast.dtype), fast.pe_table, fast.project_features)
    if fast.fused and shader.fused_available():
        dtype = "bf16 hidden layers" if shader.fused_bf16() else "fp32"
        return RenderPath(f"fast path, {uvs}, {frames}; fused C pass ({dtype})", False)
    why = "--no-fused-shade" if not fast.fused else "the fused C kernel did not build (deliffas.native)"
    return RenderPath(f"fast path, {uvs}, {frames}; per-stage shading ({why}), MLP in {str(mlp_dtype(fast.dtype))[6:]}",
                      fast.fused)


# one shader per model, alive as long as it
_SHADERS: "weakref.WeakKeyDictionary[DeliffasModel, dict[tuple[torch.dtype, bool, bool], FastShader]]" = \
    weakref.WeakKeyDictionary()


def _shader(model: DeliffasModel, dtype: torch.dtype, pe_table: bool, project_features: bool) -> FastShader:
    per_model = _SHADERS.setdefault(model, {})
    key = (dtype, pe_table, project_features)
    if key not in per_model:
        per_model[key] = FastShader(model, dtype, pe_table=pe_table, project_features=project_features)
    return per_model[key]


def _camera_batch(rays: CameraRays) -> RayBatch:
    """``stack_rays([rays], [0])`` without copies: the batch's tensors share ``rays``' arrays or tensors (fresh
    ones from ``device_camera_rays``); ``viewdir`` None where the rays have none."""
    zeros = torch.zeros(rays.num_rays, dtype=torch.long)
    as_t = torch.as_tensor
    return RayBatch(batch_index=zeros, image_index=zeros, pixels=as_t(rays.pixels), uv_inner=as_t(rays.uv_inner),
                    uv_outer=as_t(rays.uv_outer), inner_from_outer=as_t(rays.inner_from_outer),
                    viewdir=as_t(rays.viewdir) if rays.viewdir is not None else None)  # type: ignore[arg-type]


@torch.no_grad()
def fast_render_camera(model: DeliffasModel, features: FrameFeatures, raycaster: UVRaycaster, camera: Camera,
                       timer: StageTiming, fast: RenderPathConfig = RenderPathConfig(),
                       background: float = 0.0) -> torch.Tensor:
    """One camera's (H, W, 3) float32 image on ``background``, as ``render_camera`` on CPU (stages uv, sample, mlp),
    by the fast path's knobs of ``fast`` (its ``path`` is the caller's choice), the uvs from ``fast.uv``.

    Variants :class:`FastShader` does not support keep the model's own ``gather_inputs`` and MLP."""
    with timer.stage("uv"):
        # view directions only for the variants that read them (ray_query passes them on only then)
        batch = _camera_batch(device_camera_rays(raycaster, camera, "cpu", fast.uv, viewdir=model.spec.viewdir))
        query = ray_query(batch, model.spec)
    if supports(model) and model.mlp.output.weight.dtype == torch.float32 and features.inner.device.type == "cpu":
        shader = _shader(model, mlp_dtype(fast.dtype), fast.pe_table, fast.project_features)
        if fast.fused and shader.fused_available():
            with timer.stage("mlp"):  # sampling, encodings and the MLP in one pass: timed as one stage
                canvas = torch.full((camera.height * camera.width, 3), float(background))
                out = shader.shade_fused(features, query, out=canvas, rows=batch.pixels)
                return out.view(camera.height, camera.width, 3)
        with timer.stage("sample"):
            enc, feats = shader.inputs(features, query)
        with timer.stage("mlp"):  # the output layer writes each colour to its pixel
            canvas = torch.full((camera.height * camera.width, 3), float(background))
            return shader.mlp(enc, feats, out=canvas, rows=batch.pixels).view(camera.height, camera.width, 3)
    else:
        with timer.stage("sample"):
            enc, feats = model.gather_inputs(features, query)
        with timer.stage("mlp"):
            rgb = model.mlp(enc, feats)
    return paint_images(rgb, batch, 1, camera.height, camera.width, background)[0]


def render_stream(render: Callable[[T], R], items: Iterable[T], in_flight: int = 2) -> Iterator[R]:
    """``render(item)`` of each item, in order, with up to ``in_flight`` items rendering at once.

    ``in_flight`` > 1: worker threads, each item on one torch intra-op thread (set for the stream's
    duration, then restored: two single-thread frames on two cores beat one frame on two threads,
    whose many short parallel regions wait for each other; see docs/performance.md). ``render``
    must be safe to call from several threads at once (the fast path is: per-call buffers,
    per-thread rasteriser scratch). ``in_flight`` = 1: sequentially in the caller's thread, at the
    process's thread count (the plain path)."""
    if in_flight < 1:
        raise ValueError(f"render_stream: in_flight must be >= 1, got {in_flight}")
    if in_flight == 1:
        for item in items:
            yield render(item)
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    pending: collections.deque = collections.deque()
    pool = ThreadPoolExecutor(max_workers=in_flight, thread_name_prefix="render")
    try:
        for item in items:
            pending.append(pool.submit(render, item))
            if len(pending) >= in_flight:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        for fut in pending:
            fut.cancel()
        pool.shutdown(wait=True)
        torch.set_num_threads(threads)
