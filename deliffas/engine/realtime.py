"""The fast path of free-viewpoint rendering on CPU: rasterised uvs, fused per-ray inputs, an MLP in bf16 where native.

A camera's image is rendered here as :func:`deliffas.engine.evaluate.render_camera` renders it,
stage by stage (``uv``, ``sample``, ``mlp``), with three replacements:

* ``uv``: :class:`~deliffas.geometry.rasterize.UVRasterizer` instead of the open3d ray caster (same
  shaded pixels and uvs; the ray caster is used where a vertex is behind the camera);
* ``sample``: :class:`~deliffas.models.fast_shade.FastShader` writes the encodings and sampled
  features straight into the MLP's operands (one C pass);
* ``mlp``: the MLP as a chain of ``addmm`` in fp32, or in bf16 where the CPU has native bf16;
* by default ``sample`` and ``mlp`` are one C pass instead (``FastShader.shade_fused``: 16 rays at a time in
  the vector lanes, the hidden layers in bf16 with native bf16 dot products where the dtype is bf16, else fp32,
  the first layer's encoded part from per-coordinate tables in fp32 (``FastRender.pe_table``), the feature
  layer's feature part sampled from maps projected once per frame's features (``FastRender.project_features``);
  every colour written to its pixel), timed as the ``mlp`` stage.

:class:`FastRender` is the switch. ``deliffas render`` and ``deliffas view`` use
:func:`default_fast_render` (on for CPU devices); ``deliffas eval`` keeps the plain path, whose
numbers are the reference. The environment variable ``DELIFFAS_FAST_RENDER=0`` turns the fast
path off everywhere, ``DELIFFAS_RENDER_DTYPE=float32`` keeps the MLP in fp32.

:func:`render_stream` keeps two frames in flight on a 2-core CPU: each frame renders in a worker
thread on one torch intra-op thread (every stage releases the GIL: oneDNN, the C kernels through
ctypes, open3d), so consecutive frames overlap on the two cores and come out in order, identical to
the sequential path (``in_flight=1``; ``DELIFFAS_FRAMES_IN_FLIGHT=1``).
"""

from __future__ import annotations

import collections
import logging
import os
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Literal, TypeVar

import torch

from deliffas.engine.rays import CameraRays, RayBatch, camera_rays, paint_images, ray_query
from deliffas.engine.timing import StageTimer
from deliffas.geometry.rasterize import UVRasterizer
from deliffas.geometry.raycast import UVRaycaster
from deliffas.io.cameras import Camera
from deliffas.models.deliffas import DeliffasModel, FrameFeatures
from deliffas.models.fast_shade import FastShader, native_bf16, supports

__all__ = ["FastRender", "default_fast_render", "fast_camera_rays", "fast_render_camera", "render_stream",
           "FAST_RENDER_ENV", "RENDER_DTYPE_ENV", "FUSED_SHADE_ENV", "PE_TABLE_ENV", "PROJECT_FEATURES_ENV",
           "FRAMES_IN_FLIGHT_ENV"]

logger = logging.getLogger(__name__)

FAST_RENDER_ENV = "DELIFFAS_FAST_RENDER"
"""Environment variable: "0" makes :func:`default_fast_render` return None (the plain path)."""
RENDER_DTYPE_ENV = "DELIFFAS_RENDER_DTYPE"
"""Environment variable: "float32" or "bfloat16" overrides ``FastRender.dtype="auto"``."""

FUSED_SHADE_ENV = "DELIFFAS_FUSED_SHADE"
"""Environment variable: "0" makes :func:`default_fast_render` use the per-stage path (``FastRender.fused=False``)."""
PE_TABLE_ENV = "DELIFFAS_PE_TABLE"
"""Environment variable: "0" makes :func:`default_fast_render` encode every ray exactly (``FastRender.pe_table=False``)."""
PROJECT_FEATURES_ENV = "DELIFFAS_PROJECT_FEATURES"
"""Environment variable: "0" makes :func:`default_fast_render` sample the features themselves
(``FastRender.project_features=False``)."""
FRAMES_IN_FLIGHT_ENV = "DELIFFAS_FRAMES_IN_FLIGHT"
"""Environment variable: frames :func:`render_stream` renders at once under ``FastRender.in_flight=0`` (auto);
"1" = one after the other."""

Dtype = Literal["auto", "float32", "bfloat16"]
T = TypeVar("T")
R = TypeVar("R")


@dataclass(frozen=True)
class FastRender:
    """How the fast path renders."""

    rasterize: bool = True
    """uvs by rasterisation (False: the open3d ray caster, as the plain path)."""
    dtype: Dtype = "auto"
    """The MLP's dtype: "auto" = bf16 where the CPU has native bf16, else fp32."""
    fused: bool = True
    """Sampling, encodings and the whole MLP in one C pass (``FastShader.shade_fused``): its hidden layers in bf16
    when ``dtype`` resolves to bf16 and the kernel has native bf16 dot products, else in fp32; False = the
    per-stage path (inputs, then the MLP in ``dtype``). ``DELIFFAS_FUSED_SHADE=0`` turns it off."""
    pe_table: bool = True
    """The fused fp32 pass takes the first layer's encoded part from per-coordinate tables
    (``FastShader.encoding_table``: within 1e-4 of the exact pass, about 95 dB); False = the exact encoding.
    ``DELIFFAS_PE_TABLE=0`` turns it off."""
    project_features: bool = True
    """The fused fp32 pass samples the feature layer's feature part from maps projected once per frame's features
    (``FastShader.projected_maps``: the same sums in another order, within 1e-6) instead of sampling the features
    and multiplying; False = the features. ``DELIFFAS_PROJECT_FEATURES=0`` turns it off."""
    in_flight: int = 0
    """Frames :func:`render_stream` renders at once: 0 = auto (``DELIFFAS_FRAMES_IN_FLIGHT``, else one per CPU
    core, at most 2), 1 = sequentially."""

    def __post_init__(self) -> None:
        if self.dtype not in ("auto", "float32", "bfloat16"):
            raise ValueError(f"FastRender: dtype must be auto, float32 or bfloat16, got {self.dtype!r}")
        if not isinstance(self.in_flight, int) or self.in_flight < 0:
            raise ValueError(f"FastRender: in_flight must be an int >= 0 (0 = auto), got {self.in_flight!r}")

    def frames_in_flight(self) -> int:
        """The resolved number of frames in flight (>= 1)."""
        if self.in_flight:
            return self.in_flight
        env = os.environ.get(FRAMES_IN_FLIGHT_ENV, "").strip()
        if env:
            if not env.isdigit() or int(env) < 1:
                raise ValueError(f"{FRAMES_IN_FLIGHT_ENV} must be an integer >= 1, got {env!r}")
            return int(env)
        return max(1, min(2, os.cpu_count() or 1))

    def torch_dtype(self) -> torch.dtype:
        """The resolved MLP dtype."""
        name = self.dtype
        if name == "auto":
            name = os.environ.get(RENDER_DTYPE_ENV, "").strip() or ("bfloat16" if native_bf16() else "float32")
            if name not in ("float32", "bfloat16"):
                raise ValueError(f"{RENDER_DTYPE_ENV} must be float32 or bfloat16, got {name!r}")
        return torch.bfloat16 if name == "bfloat16" else torch.float32


def default_fast_render(device: torch.device | str) -> FastRender | None:
    """The fast path for ``device``: on for CPU unless ``DELIFFAS_FAST_RENDER=0`` (the fused pass unless
    ``DELIFFAS_FUSED_SHADE=0``); None = the plain path."""
    if torch.device(device).type != "cpu" or os.environ.get(FAST_RENDER_ENV, "1").strip() == "0":
        return None
    return FastRender(fused=os.environ.get(FUSED_SHADE_ENV, "1").strip() != "0",
                      pe_table=os.environ.get(PE_TABLE_ENV, "1").strip() != "0",
                      project_features=os.environ.get(PROJECT_FEATURES_ENV, "1").strip() != "0")


# one rasteriser and one shader per frame geometry / model, alive as long as their owner
_RASTERIZERS: "weakref.WeakKeyDictionary[UVRaycaster, UVRasterizer]" = weakref.WeakKeyDictionary()
_SHADERS: "weakref.WeakKeyDictionary[DeliffasModel, dict[tuple[torch.dtype, bool, bool], FastShader]]" = \
    weakref.WeakKeyDictionary()


def _rasterizer(raycaster: UVRaycaster) -> UVRasterizer:
    rz = _RASTERIZERS.get(raycaster)
    if rz is None:
        rz = _RASTERIZERS[raycaster] = UVRasterizer(raycaster.inner_verts, raycaster.faces, raycaster.outer_verts,
                                                    raycaster.atlas)
    return rz


def _shader(model: DeliffasModel, dtype: torch.dtype, pe_table: bool, project_features: bool) -> FastShader:
    per_model = _SHADERS.setdefault(model, {})
    key = (dtype, pe_table, project_features)
    if key not in per_model:
        per_model[key] = FastShader(model, dtype, pe_table=pe_table, project_features=project_features)
    return per_model[key]


def fast_camera_rays(raycaster: UVRaycaster, camera: Camera, rasterize: bool = True, viewdir: bool = True) -> CameraRays:
    """``camera_rays(raycaster, camera)`` by rasterisation (the ray caster where a vertex is behind the camera);
    ``viewdir=False``: the rasteriser leaves the view directions out (``viewdir`` None)."""
    got = _rasterizer(raycaster).shaded_pixels(camera, viewdir) if rasterize else None
    if got is None:
        return camera_rays(raycaster, camera)
    return CameraRays(pixels=got.pixels, uv_inner=got.uv_inner, inner_from_outer=got.inner_from_outer,
                      uv_outer=got.uv_outer, viewdir=got.viewdir, height=camera.height, width=camera.width)


def _camera_batch(rays: CameraRays) -> RayBatch:
    """``stack_rays([rays], [0])`` without copies: the batch's tensors share ``rays``' arrays (fresh ones from
    :func:`fast_camera_rays`; the copies took 0.6 ms a 940 x 1285 frame); ``viewdir`` None where the rays have none."""
    zeros = torch.zeros(rays.num_rays, dtype=torch.long)
    return RayBatch(batch_index=zeros, image_index=zeros, pixels=torch.from_numpy(rays.pixels),
                    uv_inner=torch.from_numpy(rays.uv_inner), uv_outer=torch.from_numpy(rays.uv_outer),
                    inner_from_outer=torch.from_numpy(rays.inner_from_outer),
                    viewdir=torch.from_numpy(rays.viewdir) if rays.viewdir is not None else None)  # type: ignore[arg-type]


@torch.no_grad()
def fast_render_camera(model: DeliffasModel, features: FrameFeatures, raycaster: UVRaycaster, camera: Camera,
                       timer: StageTimer, fast: FastRender = FastRender(), background: float = 0.0) -> torch.Tensor:
    """One camera's (H, W, 3) float32 image on ``background``, as ``render_camera`` on CPU (stages uv, sample, mlp).

    Variants :class:`FastShader` does not support keep the model's own ``gather_inputs`` and MLP."""
    with timer.stage("uv"):
        # view directions only for the variants that read them (ray_query passes them on only then)
        batch = _camera_batch(fast_camera_rays(raycaster, camera, fast.rasterize, viewdir=model.spec.viewdir))
        query = ray_query(batch, model.spec)
    if supports(model) and model.mlp.output.weight.dtype == torch.float32 and features.inner.device.type == "cpu":
        shader = _shader(model, fast.torch_dtype(), fast.pe_table, fast.project_features)
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
