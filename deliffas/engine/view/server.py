"""The viser wiring of ``deliffas view``: GUI, scene (frustums, meshes), cameras and the render loop.

Each connected browser gets a :class:`~deliffas.engine.view.renderer.RenderWorker`; camera moves and
GUI changes submit requests to it (lower resolution and JPEG while the camera moves, full
resolution and PNG once it is still) and its results become the scene's background image. The
viser scene is in metres (deliffas mm / 1000), y up; viser's cameras, like deliffas's, look along
+z with image y down, so a pose converts by the rotation alone.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
import warnings
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from deliffas.engine.view_config import ViewConfig
from deliffas.engine.view.renderer import (
    VIEW_MODES,
    RenderWorker,
    ViewRenderer,
    ViewRequest,
    ViewResult,
    fit_camera,
    scaled_request,
)
from deliffas.engine.view.scene import ViewScene
from deliffas.io.cameras import Camera
from deliffas.native import build_declared
from deliffas.optional import import_optional

__all__ = ["serve", "viewer_camera", "capture_camera_pose", "import_viser", "departures_quiet", "log_departure",
           "CaptureHold", "MM_PER_UNIT",
           "ECHO_TIMEOUT_S"]

logger = logging.getLogger(__name__)

MM_PER_UNIT = 1000.0
"""deliffas world millimetres per viser scene unit (the scene is in metres)."""
_FREE = "free camera"
_TICK_S = 0.03
ECHO_TIMEOUT_S = 10.0
"""Seconds after a move to a capture camera within which the browser must report that pose back; a
camera that never showed it by then counts as moved away by the user (see :class:`CaptureHold`)."""


def import_viser():
    need = "deliffas view needs the 'viser' package (pip install viser)"
    return import_optional("viser", need), import_optional("viser.transforms", need)


DEPARTED_CLIENT_WARNING = r"Queued a \w+ on a closed connection"
"""viser's UserWarning for a message sent to a browser tab that has left (a frame rendered for it while it closed):
expected in a viewer, not a fault; :func:`log_departure` says that the tab left instead."""


@contextmanager
def departures_quiet():
    """While a viewer serves: viser's departed-client warning is not shown (every other warning is)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=DEPARTED_CLIENT_WARNING, category=UserWarning)
        yield


def log_departure(client) -> None:
    """One info line when a browser tab leaves the viewer."""
    logger.info("deliffas view: client %d disconnected", client.client_id)


def viewer_camera(wxyz: np.ndarray, position: np.ndarray, fov: float, width: int, height: int,
                  max_side: int) -> Camera:
    """The deliffas camera of a viser view: rotation ``wxyz`` (camera -> world), ``position`` (scene
    units), vertical ``fov`` (radians), canvas ``width`` x ``height`` scaled so its longest side is at
    most ``max_side``; principal point at the image centre."""
    _, vtf = import_viser()
    s = min(1.0, max_side / max(width, height))
    w, h = max(8, round(width * s)), max(8, round(height * s))
    f = h / 2 / math.tan(fov / 2)
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    R = vtf.SO3(np.asarray(wxyz, np.float64)).as_matrix().T  # world -> camera
    world_to_cam = np.eye(4)
    world_to_cam[:3, :3] = R
    world_to_cam[:3, 3] = -R @ (np.asarray(position, np.float64) * MM_PER_UNIT)
    return Camera("viewer", K, world_to_cam, w, h)


def capture_camera_pose(camera: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(wxyz, position in scene units, vertical fov in radians) of a capture camera for viser."""
    _, vtf = import_viser()
    wxyz = vtf.SO3.from_matrix(camera.R.T).wxyz
    fov = 2 * math.atan(camera.height / 2 / camera.K[1, 1])
    return wxyz, camera.center / MM_PER_UNIT, fov


@dataclass
class CaptureHold:
    """A browser view sent to a capture camera's pose, and whether the browser has reported that pose back.

    The browser applies the pose field by field (position, look-at, orientation) and reports each
    intermediate camera, so a camera away from the pose means "the user moved away" only after the
    pose itself was reported once. A timer alone misjudges this on a loaded machine, where the
    reports arrive late (a CI run saw the overlay dropped that way)."""

    camera: int
    wxyz: np.ndarray
    position: np.ndarray
    entered: float
    """When the view was sent to the pose (perf_counter seconds)."""
    reached: bool = False

    @classmethod
    def sent(cls, camera: int, wxyz, position) -> "CaptureHold":
        """The hold of a view sent to capture camera ``camera``'s pose (``capture_camera_pose``) now."""
        return cls(camera, np.asarray(wxyz), np.asarray(position), time.perf_counter())

    def at_pose(self, wxyz, position) -> bool:
        return bool(np.abs(np.asarray(position) - self.position).max() < 1e-3  # 1 mm
                    and 1 - abs(float(np.dot(np.asarray(wxyz), self.wxyz))) < 2e-5)  # about 0.7 degrees

    def left(self, wxyz, position, now: float) -> bool:
        """Whether a reported camera (``wxyz``, ``position`` in scene units) at ``now`` leaves the pose."""
        if self.at_pose(wxyz, position):
            self.reached = True
            return False
        return self.reached or now - self.entered >= ECHO_TIMEOUT_S


@dataclass
class _ClientView:
    """What the viewer keeps per browser tab."""

    client: object
    worker: RenderWorker | None = None
    hold: CaptureHold | None = None
    """The capture camera the view looks through; None for a free camera."""
    last_move: float = 0.0
    refined: bool = True
    serial: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)


class _Viewer:
    """The GUI of one server: shared controls, one render worker per client."""

    def __init__(self, cfg: ViewConfig, scene: ViewScene, server, vtf):
        self.cfg, self.scene, self.server, self.vtf = cfg, scene, server, vtf
        self.renderer = ViewRenderer(scene, cfg.chunk_size, cfg.render_path)
        self.clients: dict[int, _ClientView] = {}
        self.render_lock = threading.Lock()  # workers share the models and caches: one frame at a time
        self._build_gui()
        self._build_scene()

    # ----------------------------------------------------------------- GUI
    def _build_gui(self) -> None:
        gui, sc = self.server.gui, self.scene
        cams = [_FREE] + [self._camera_label(c) for c in sc.converted_cameras]
        first = sc.test_cameras[0] if sc.test_cameras else sc.converted_cameras[0]
        with gui.add_folder("Camera"):
            self.camera_menu = gui.add_dropdown("capture camera", cams, initial_value=self._camera_label(first),
                                                hint="move the view to a capture camera (drag to fly freely)")
            self.show_frustums = gui.add_checkbox("show cameras", True)
        with gui.add_folder("Timeline"):
            self.frame = gui.add_slider("frame", 0, max(sc.num_frames - 1, 1), 1, 0, disabled=sc.num_frames < 2,
                                        hint=sc.source)
            self.playing = gui.add_checkbox("play", False)
            self.speed = gui.add_slider("speed (frames/s)", 1.0, 30.0, 1.0, 10.0)
        with gui.add_folder("View"):
            self.mode = gui.add_dropdown("view", VIEW_MODES, initial_value="rgb")
            runs = [r.name for r in sc.runs]
            options = runs + (["side by side"] if len(runs) > 1 else [])
            self.run_menu = gui.add_dropdown("run", options, initial_value=options[-1] if len(runs) > 1 else runs[0])
            self.show_gt = gui.add_checkbox("ground truth + error", True,
                                            hint="at a capture camera and a captured frame")
            self.show_inner = gui.add_checkbox("inner mesh", False)
            self.show_outer = gui.add_checkbox("outer mesh", False)
            self.max_res = gui.add_slider("resolution", 64, 2048, 32, self.cfg.max_resolution,
                                          hint="longest side while still; x moving_scale while moving")
        with gui.add_folder("Timing"):
            self.timing = gui.add_markdown("waiting for the first frame")

        @self.camera_menu.on_update
        def _(event) -> None:
            if self.camera_menu.value == _FREE:
                return
            targets = [event.client] if event.client is not None else list(self.server.get_clients().values())
            for client in targets:
                self._goto_capture(client, self._camera_id(self.camera_menu.value))

        for handle in (self.frame, self.mode, self.run_menu, self.show_gt, self.max_res):
            handle.on_update(lambda _event: self._rerender_all())
        for handle in (self.frame, self.show_inner, self.show_outer):
            handle.on_update(lambda _event: self._update_meshes())
        self.show_frustums.on_update(lambda _event: self._toggle_frustums())

    def _camera_label(self, cam_id: int) -> str:
        test = " (test)" if cam_id in self.scene.test_cameras else ""
        return f"{cam_id}: {self.scene.cameras[cam_id].name}{test}"

    def _camera_id(self, label: str) -> int:
        return int(label.split(":", 1)[0])

    def _build_scene(self) -> None:
        sc, scene = self.scene, self.server.scene
        scene.set_up_direction("+y")
        self.frustums: dict[int, object] = {}
        for cam_id in sc.converted_cameras:
            cam = sc.cameras[cam_id]
            wxyz, position, fov = capture_camera_pose(cam)
            color = (230, 60, 60) if cam_id in sc.test_cameras else (60, 60, 230)
            handle = scene.add_camera_frustum(f"/cameras/{cam_id}", fov, cam.width / cam.height, scale=0.12,
                                              color=color, wxyz=wxyz, position=position)
            handle.on_click(lambda event, c=cam_id: self._goto_capture(event.client, c))
            self.frustums[cam_id] = handle
        first = sc.test_cameras[0] if sc.test_cameras else sc.converted_cameras[0]
        wxyz, position, fov = capture_camera_pose(sc.cameras[first])
        init = self.server.initial_camera
        init.position, init.look_at, init.fov = position, self._look_at(sc.cameras[first]), fov
        self.meshes: dict[str, object] = {}

    def _look_at(self, cam: Camera) -> np.ndarray:
        """The point the capture camera looks at, at the avatar's depth (the orbit centre), scene units."""
        centre = self.scene.frame(self.frame.value if hasattr(self, "frame") else 0).inner_verts.mean(0)
        depth = max(float((cam.R @ centre + cam.t)[2]), 1.0)
        return (cam.center + cam.R[2] * depth) / MM_PER_UNIT

    def _toggle_frustums(self) -> None:
        """Frustums shown when asked, except those a browser looks through (they would frame its view)."""
        inside = {hold.camera for hold in [v.hold for v in list(self.clients.values())] if hold is not None}
        for cam_id, h in self.frustums.items():
            visible = bool(self.show_frustums.value) and cam_id not in inside
            if h.visible != visible:
                h.visible = visible

    def _update_meshes(self) -> None:
        data = self.scene.frame(self.frame.value)
        for name, show, verts, color, opacity in (("inner", self.show_inner.value, data.inner_verts, (200, 170, 140), None),
                                                  ("outer", self.show_outer.value, data.outer_verts, (90, 200, 255), 0.35)):
            if show:
                self.meshes[name] = self.server.scene.add_mesh_simple(
                    f"/avatar/{name}", verts / MM_PER_UNIT, self.scene.faces, color=color, opacity=opacity,
                    side="double")
            elif name in self.meshes:
                self.meshes.pop(name).remove()

    def warm_up(self) -> None:
        """Build the C kernels (all at once) and render one small frame while the first browser loads the page, so
        that its first frame needs no compiler (a cold first render builds the libraries one after another)."""
        try:
            build_declared()
            cam_id = self.scene.test_cameras[0] if self.scene.test_cameras else self.scene.converted_cameras[0]
            camera = fit_camera(self.scene.cameras[cam_id], 64, 64, upscale=False)
            self.renderer_locked().render(ViewRequest(camera, 0, "rgb", capture_camera=cam_id))
        except Exception as err:  # noqa: BLE001 - the first client's own render reports any error
            logger.debug("deliffas view: warm-up failed: %s", err)

    # ------------------------------------------------------------- clients
    def connect(self, client) -> None:
        view = _ClientView(client)
        view.worker = RenderWorker(self.renderer_locked(), lambda result: self._show(view, result),
                                   lambda err: setattr(self.timing, "content", f"render error: {err}"))
        self.clients[client.client_id] = view
        client.camera.on_update(lambda _camera: self._moved(view))
        label = self.camera_menu.value
        if label != _FREE:
            self._goto_capture(client, self._camera_id(label))
        else:
            self._submit(view, moving=False)

    def disconnect(self, client) -> None:
        log_departure(client)
        view = self.clients.pop(client.client_id, None)
        if view is not None and view.worker is not None:
            view.worker.stop(timeout=0)

    def renderer_locked(self):
        """The shared renderer behind ``render_lock`` (two tabs must not render at once on 2 cores)."""
        viewer = self

        class _Locked:
            def render(self, request):
                with viewer.render_lock:
                    return viewer.renderer.render(request)

        return _Locked()

    def _goto_capture(self, client, cam_id: int) -> None:
        view = self.clients.get(client.client_id)
        if view is None:
            return
        cam = self.scene.cameras[cam_id]
        wxyz, position, fov = capture_camera_pose(cam)
        with view.lock:
            view.hold = CaptureHold.sent(cam_id, wxyz, position)
        self._toggle_frustums()
        with client.atomic():
            client.camera.fov = fov
            client.camera.position = position
            client.camera.look_at = self._look_at(cam)
            client.camera.wxyz = wxyz
        self._submit(view, moving=False)

    def _moved(self, view: _ClientView) -> None:
        cam, hold = view.client.camera, view.hold
        if hold is not None and hold.left(cam.wxyz, cam.position, time.perf_counter()):
            with view.lock:
                view.hold = None
            self._toggle_frustums()
            self.camera_menu.value = _FREE  # so that choosing the same camera again moves back to it
        with view.lock:
            view.last_move, view.refined = time.perf_counter(), False
        self._submit(view, moving=True)

    def _rerender_all(self) -> None:
        for view in list(self.clients.values()):
            self._submit(view, moving=False)

    def tick(self) -> None:
        """Called every few ms: refine views whose camera came to rest."""
        now = time.perf_counter()
        for view in list(self.clients.values()):
            if not view.refined and now - view.last_move >= self.cfg.still_after_s:
                view.refined = True
                self._submit(view, moving=False)

    def _request(self, view: _ClientView, moving: bool) -> ViewRequest:
        cam = view.client.camera
        canvas = (int(cam.image_width), int(cam.image_height))
        run = self.run_menu.value
        names = [r.name for r in self.scene.runs]
        runs = tuple(range(len(names))) if run == "side by side" else (names.index(run),)
        with view.lock:
            view.serial += 1
            capture = view.hold.camera if view.hold is not None else None
            serial = view.serial
        if capture is not None:  # the capture camera itself (its own intrinsics), at most the still size
            side = self.max_res.value
            camera = fit_camera(self.scene.cameras[capture], side, side, upscale=False)
        else:
            camera = viewer_camera(cam.wxyz, cam.position, cam.fov, *canvas, self.max_res.value)
        request = ViewRequest(camera, int(self.frame.value), self.mode.value, runs, capture,
                              bool(self.show_gt.value), canvas, serial)
        return scaled_request(request, self.cfg.moving_scale) if moving else request

    def _submit(self, view: _ClientView, moving: bool) -> None:
        if view.worker is not None:
            view.worker.submit(self._request(view, moving))

    def _show(self, view: _ClientView, result: ViewResult) -> None:
        moving = not view.refined
        view.client.scene.set_background_image(result.image, format="jpeg" if moving else "png",
                                               jpeg_quality=self.cfg.jpeg_quality)
        ms = result.stage_ms
        fps = 1000.0 / result.wall_ms if result.wall_ms > 0 else float("inf")
        w, h = result.panel_size
        self.timing.content = (
            f"**{fps:.1f} fps** ({result.wall_ms:.0f} ms), {w}×{h}{' (moving)' if moving else ''}  \n"
            + " · ".join(f"{k} {ms.get(k, 0.0):.1f}" for k in ("uv", "cnn", "sample", "mlp")) + " ms  \n"
            + f"frame {self.scene.frame_labels[min(result.request.frame, self.scene.num_frames - 1)]}, "
            + (f"camera {result.request.capture_camera}" if result.request.capture_camera is not None else "free camera")
            + f"  \npanels: {', '.join(result.panels)}  \nrendered {view.worker.rendered}, dropped {view.worker.dropped}")

    def play(self) -> None:
        """Advance the timeline while 'play' is checked (called from the main loop)."""
        self.frame.value = (int(self.frame.value) + 1) % self.scene.num_frames


def serve(cfg: ViewConfig, stop: threading.Event | None = None, ready: Callable[[], None] | None = None) -> None:
    """Serve the viewer at ``cfg.host:cfg.port`` until interrupted (or ``stop`` is set); ``ready`` is called once
    the runs are loaded and the server listens (the CLI prints the address then, not before a failure)."""
    viser, vtf = import_viser()
    if cfg.exposed:
        logger.warning("deliffas view: listening on %s: anyone who can reach this machine can see the viewer "
                       "(no authentication); prefer 127.0.0.1 and SSH port forwarding", cfg.host)
    scene = ViewScene([cfg.run] + ([cfg.compare] if cfg.compare else []), cfg.shards, cfg.motion, cfg.device,
                      cfg.max_frames)
    server = viser.ViserServer(host=cfg.host, port=cfg.port, label="deliffas view", verbose=False)
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():  # SIGTERM (a service manager, a test) stops cleanly
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with departures_quiet():
        try:
            viewer = _Viewer(cfg, scene, server, vtf)
            threading.Thread(target=viewer.warm_up, name="view-warm-up", daemon=True).start()
            server.on_client_connect(viewer.connect)
            server.on_client_disconnect(viewer.disconnect)
            logger.info("deliffas view: http://%s:%d (%d frames, %d runs)", cfg.host, cfg.port, scene.num_frames,
                        len(scene.runs))
            if ready is not None:
                ready()
            next_frame = time.perf_counter()
            while not stop.is_set():
                time.sleep(_TICK_S)
                viewer.tick()
                if viewer.playing.value and time.perf_counter() >= next_frame:
                    viewer.play()
                    next_frame = time.perf_counter() + 1.0 / max(float(viewer.speed.value), 1e-3)
        finally:
            for view in list(viewer.clients.values()) if "viewer" in locals() else []:
                view.worker.stop(timeout=1)
            server.stop()
