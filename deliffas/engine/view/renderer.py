"""The viewer's renderer: a frame request (camera, timeline position, view) in, one image out.

No GUI here: :class:`ViewRenderer` is a pure function of its request (plus caches), and
:class:`RenderWorker` runs it on a thread that always takes the newest request and drops the stale
ones, so the GUI never waits for a frame. RGB images come from the engine's renderer
(``render_camera``, the U-Nets once per frame and cached); the other views paint the same shaded
rays with their uvs, temporal normals or U-Net features (first 3 PCA components).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Callable, Literal

import numpy as np
import torch

from deliffas.engine.shading import render_camera
from deliffas.fast.config import RenderPathConfig
from deliffas.fast.frame import describe_render_path, path_for_device
from deliffas.engine.rays import camera_rays, paint_images, stack_rays
from deliffas.engine.timing import STAGES, StageTimer
from deliffas.engine.view.scene import FrameData, ViewScene
from deliffas.geometry.sampling import sample_uv
from deliffas.io.cameras import Camera
from deliffas.models.deliffas import FrameFeatures

__all__ = ["VIEW_MODES", "ViewRequest", "ViewResult", "ViewRenderer", "RenderWorker", "fit_camera", "heat_map",
           "scaled_request", "panel_grid", "compose_panels"]

logger = logging.getLogger(__name__)

ViewMode = Literal["rgb", "uv_inner", "uv_outer", "normals_inner", "normals_outer", "features_inner",
                   "features_outer"]
VIEW_MODES: tuple[str, ...] = ("rgb", "uv_inner", "uv_outer", "normals_inner", "normals_outer", "features_inner",
                               "features_outer")

_CACHED_FEATURES = 4


@dataclass(frozen=True)
class ViewRequest:
    """One image the viewer wants.

    Attributes:
        camera: the view, its intrinsics for the wanted render size.
        frame: timeline position.
        mode: what to paint (``VIEW_MODES``).
        runs: indices of the scene's runs, side by side (left to right).
        capture_camera: the capture camera ``camera`` is (any size), or None for a free camera;
            with a captured frame it adds the ground truth and the error heat map of the first run.
        show_ground_truth: whether to add those panels when possible.
        canvas: (W, H) of the client's canvas; the panels are letterboxed to its aspect.
        serial: increasing request number (larger = newer).
    """

    camera: Camera
    frame: int
    mode: str = "rgb"
    runs: tuple[int, ...] = (0,)
    capture_camera: int | None = None
    show_ground_truth: bool = True
    canvas: tuple[int, int] | None = None
    serial: int = 0


@dataclass(frozen=True)
class ViewResult:
    """A rendered request.

    Attributes:
        request: what was asked.
        image: (H, W, 3) uint8 RGB, the panels on a grid (``panel_grid``) letterboxed to the canvas aspect on black.
        panels: the panels' titles, left to right.
        stage_ms: milliseconds per stage (uv, cnn, sample, mlp; cnn 0 when the frame's features were cached).
        wall_ms: wall time of the whole request.
        panel_size: (W, H) of each panel.
    """

    request: ViewRequest
    image: np.ndarray
    panels: tuple[str, ...]
    stage_ms: dict[str, float] = field(default_factory=dict)
    wall_ms: float = 0.0
    panel_size: tuple[int, int] = (0, 0)


def fit_camera(camera: Camera, width: int, height: int, upscale: bool = True) -> Camera:
    """``camera`` uniformly scaled to fit in ``width`` x ``height`` (aspect kept; no enlarging unless ``upscale``)."""
    s = min(width / camera.width, height / camera.height)
    if not upscale:
        s = min(s, 1.0)
    w, h = max(1, round(camera.width * s)), max(1, round(camera.height * s))
    return camera if (w, h) == (camera.width, camera.height) else camera.rescaled(w, h)


def heat_map(error: np.ndarray, vmax: float = 0.25) -> np.ndarray:
    """(H, W, 3) float colours of an (H, W) error in [0, ``vmax``]: black -> red -> yellow -> white."""
    x = np.clip(error / vmax, 0, 1)
    return np.stack([np.clip(3 * x, 0, 1), np.clip(3 * x - 1, 0, 1), np.clip(3 * x - 2, 0, 1)], -1).astype(np.float32)


def panel_grid(n: int, panel: tuple[int, int], canvas: tuple[int, int] | None) -> tuple[int, int]:
    """(columns, rows) of ``n`` panels of size ``panel`` (W, H) that show them largest on ``canvas`` (W, H)."""
    if canvas is None:
        return n, 1
    pw, ph = panel
    cols = max(range(1, n + 1), key=lambda c: (min(canvas[0] / (c * pw), canvas[1] / (-(-n // c) * ph)), -c))
    return cols, -(-n // cols)


def compose_panels(panels: list[np.ndarray], canvas: tuple[int, int] | None) -> np.ndarray:
    """Equal-size (H, W, 3) panels on a grid (``panel_grid``), centred on black with the aspect of ``canvas``."""
    h, w = panels[0].shape[:2]
    cols, rows = panel_grid(len(panels), (w, h), canvas)
    grid = np.zeros((rows * h, cols * w, 3), panels[0].dtype)
    for i, p in enumerate(panels):
        r, c = divmod(i, cols)
        grid[r * h:(r + 1) * h, c * w:(c + 1) * w] = p
    if canvas is None:
        return grid
    gh, gw = grid.shape[:2]
    cw, ch = canvas
    if gw * ch >= gh * cw:  # wider than the canvas: pad rows
        out_w, out_h = gw, max(gh, round(gw * ch / cw))
    else:
        out_w, out_h = max(gw, round(gh * cw / ch)), gh
    out = np.zeros((out_h, out_w, 3), grid.dtype)
    y0, x0 = (out_h - gh) // 2, (out_w - gw) // 2
    out[y0:y0 + gh, x0:x0 + gw] = grid
    return out


class ViewRenderer:
    """Renders :class:`ViewRequest` s of a :class:`ViewScene` (the U-Nets' features cached per frame and run)."""

    def __init__(self, scene: ViewScene, chunk_size: int = 262144,
                 render_path: RenderPathConfig = RenderPathConfig(path="plain")):
        self.scene = scene
        self.chunk_size = chunk_size
        self.render_path = path_for_device(render_path, scene.device)  # the fast path on a CPU device only
        for run in scene.runs:
            path = describe_render_path(run.model, render_path, scene.device)
            logger.log(logging.WARNING if path.fallback else logging.INFO, "render path of %s: %s", run.name, path.line)
        self._features: OrderedDict[tuple[int, int], tuple[FrameFeatures, dict]] = OrderedDict()

    def features(self, run: int, frame: FrameData, timer: StageTimer) -> tuple[FrameFeatures, dict]:
        """The run's feature maps of ``frame`` (stage cnn when not cached) and their PCA bases."""
        key = (run, frame.index)
        if key in self._features:
            self._features.move_to_end(key)
            return self._features[key]
        model = self.scene.runs[run].model
        with timer.stage("cnn"), torch.no_grad():
            feats = model.encode(*frame.normal_maps(model.config.temporal_window, self.scene.device))
        self._features[key] = (feats, {})
        while len(self._features) > _CACHED_FEATURES:
            self._features.popitem(last=False)
        return self._features[key]

    @torch.no_grad()
    def render(self, request: ViewRequest) -> ViewResult:
        """The request's image: one panel per run, then ground truth and error when at a capture camera and frame."""
        t0 = time.perf_counter()
        timer = StageTimer(self.scene.device)
        frame = self.scene.frame(request.frame)
        gt = None
        if request.capture_camera is not None and request.show_ground_truth and frame.capture_frame is not None:
            gt = self.scene.ground_truth(frame.index, request.capture_camera)
        n_panels = len(request.runs) + (2 if gt is not None else 0)
        cam = request.camera
        if request.canvas is not None:  # the panels' grid fills the canvas, never above the request's size
            cols, rows = panel_grid(n_panels, (cam.width, cam.height), request.canvas)
            cam = fit_camera(cam, min(cam.width, request.canvas[0] // cols), min(cam.height, request.canvas[1] // rows))
        panels, titles = [], []
        for run in request.runs:
            panels.append(self._paint(run, frame, cam, request.mode, timer))
            titles.append(f"{self.scene.runs[run].name}: {request.mode}")
        if gt is not None:
            import cv2

            image, _mask = gt
            image = cv2.resize(image, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
            panels += [image, heat_map(np.abs(panels[0] - image).mean(-1))]
            titles += ["ground truth", "|error| (0..0.25)"]
        image = (np.clip(compose_panels(panels, request.canvas), 0, 1) * 255 + 0.5).astype(np.uint8)
        stage_ms = {s: timer.total_ms.get(s, 0.0) for s in STAGES}
        return ViewResult(request, image, tuple(titles), stage_ms, (time.perf_counter() - t0) * 1000,
                          (cam.width, cam.height))

    def _paint(self, run: int, frame: FrameData, cam: Camera, mode: str, timer: StageTimer) -> np.ndarray:
        """(H, W, 3) float32 in [0, 1] of one run's view ``mode``."""
        model = self.scene.runs[run].model
        features, pca = self.features(run, frame, timer)
        if mode == "rgb":
            return render_camera(model, features, frame.raycaster, cam, self.scene.device, timer,
                                 self.chunk_size, self.render_path).cpu().numpy()
        if mode not in VIEW_MODES:
            raise ValueError(f"view mode must be one of {VIEW_MODES}, got {mode!r}")
        with timer.stage("uv"):
            batch = stack_rays([camera_rays(frame.raycaster, cam)], [0])
        surface = mode.rsplit("_", 1)[1]
        uv = batch.uv_outer if surface == "outer" else batch.uv_inner
        with timer.stage("sample"):
            if mode.startswith("uv_"):
                colors = torch.cat([uv, torch.zeros_like(uv[:, :1])], 1)
            elif mode.startswith("normals_"):
                maps = (frame.normal_outer if surface == "outer" else frame.normal_inner)[None, :3]
                colors = (sample_uv(maps, batch.batch_index, uv) + 1) / 2
            else:
                colors = self._feature_colors(features, pca, surface, batch.batch_index, uv)
        return paint_images(colors.float().cpu(), batch, 1, cam.height, cam.width)[0].numpy()

    @staticmethod
    def _feature_colors(features: FrameFeatures, pca: dict, surface: str, batch_index, uv) -> torch.Tensor:
        """First three principal components of the U-Net features at ``uv``, scaled by the map's range."""
        maps = features.outer if surface == "outer" else features.inner
        if maps is None:
            return torch.full((uv.shape[0], 3), 0.5)
        if surface not in pca:  # basis of the texels of the whole atlas map, once per frame
            flat = maps[0].permute(1, 2, 0).reshape(-1, maps.shape[1]).float()  # (S S, C)
            mean = flat.mean(0)
            _, _, v = torch.linalg.svd(flat - mean, full_matrices=False)
            basis = v[:3].T  # (C, 3)
            proj = (flat - mean) @ basis
            pca[surface] = (mean, basis, proj.amin(0), proj.amax(0))
        mean, basis, lo, hi = pca[surface]
        feats = sample_uv(maps, batch_index.to(maps.device), uv.to(maps.device)).float()
        return ((feats - mean) @ basis - lo) / (hi - lo).clamp_min(1e-8)


class RenderWorker:
    """Renders on one thread; :meth:`submit` replaces any request still waiting (stale ones are dropped).

    Args:
        renderer: what renders.
        on_result: called on the worker thread with each :class:`ViewResult`.
        on_error: called with the exception when a request fails (the worker keeps running).
    """

    def __init__(self, renderer: ViewRenderer, on_result: Callable[[ViewResult], None],
                 on_error: Callable[[BaseException], None] | None = None):
        self.renderer, self.on_result, self.on_error = renderer, on_result, on_error
        self._pending: ViewRequest | None = None
        self._cond = threading.Condition()
        self._stopped = False
        self.rendered = 0
        self.dropped = 0
        self._thread = threading.Thread(target=self._loop, name="deliffas-view-render", daemon=True)
        self._thread.start()

    def submit(self, request: ViewRequest) -> None:
        """Ask for ``request``; a request not yet started is replaced (and counted in ``dropped``)."""
        with self._cond:
            if self._pending is not None:
                self.dropped += 1
            self._pending = request
            self._cond.notify()

    def stop(self, timeout: float | None = 5.0) -> None:
        """Finish the frame in progress, drop the rest, end the thread."""
        with self._cond:
            self._stopped = True
            self._pending = None
            self._cond.notify()
        self._thread.join(timeout)

    def _loop(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._stopped:
                    self._cond.wait()
                if self._stopped:
                    return
                request, self._pending = self._pending, None
            try:
                result = self.renderer.render(request)
            except Exception as err:  # a bad request must not end the viewer
                logger.exception("rendering request %d failed", request.serial)
                if self.on_error is not None:
                    self.on_error(err)
                continue
            self.rendered += 1
            self.on_result(result)


def scaled_request(request: ViewRequest, scale: float) -> ViewRequest:
    """``request`` with its camera at ``scale`` times the resolution (the moving-camera preview)."""
    if scale >= 1:
        return request
    cam = request.camera
    return replace(request, camera=cam.rescaled(max(8, round(cam.width * scale)), max(8, round(cam.height * scale))))
