"""``deliffas view SUBJECT``: a capture without a model in the browser (cameras, posed template, silhouette check).

:class:`SubjectView` is the GUI-free core: the capture's timeline (the frames of every sequence with pose
parameters), the posed template per frame, each camera's image, and per camera and frame the picture
``deliffas check`` reports on (the image darkened, the template's silhouette green, the mask's edge red:
:func:`deliffas.data.check_report.overlay`) with its IoU (:func:`deliffas.data.check.mask_iou`).
:func:`serve_subject` is the viser wiring: frustums textured with the current frame's images (red =
held-out), the posed template as a mesh, a camera menu (the view moves to the camera, the overlay becomes
the background, its IoU a text field) and a timeline.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from deliffas.data.check import mask_iou, posed_surface, scaled_camera, scaled_view, silhouettes
from deliffas.data.check_report import overlay
from deliffas.data.subjects import Subject, SubjectOptions, parse_subject
from deliffas.engine.view_config import SubjectViewConfig
from deliffas.engine.view.renderer import compose_panels
from deliffas.engine.view.server import (MM_PER_UNIT, CaptureHold, capture_camera_pose, departures_quiet, import_viser,
                                         log_departure)
from deliffas.geometry.templates import build_template

__all__ = ["CameraOverlay", "SubjectView", "serve_subject", "is_capture"]

logger = logging.getLogger(__name__)

_CACHED_FRAMES = 4
_FREE = "free camera"
_TICK_S = 0.03


def is_capture(path: str | os.PathLike) -> bool:
    """True when ``path`` is a folder without a run's ``train_config.json`` (so ``deliffas view`` shows a capture)."""
    p = Path(path)
    return p.is_dir() and not (p / "train_config.json").exists()


@dataclass(frozen=True)
class CameraOverlay:
    """What a capture camera shows at one timeline position.

    Attributes:
        camera: calibration index.
        index: timeline position.
        image: (h, w, 3) uint8, ``check_report.overlay`` of the camera's image, the silhouette and the mask.
        iou: silhouette vs mask IoU (pixels within the tolerance of the silhouette's edge not scored; NaN if both empty).
        silhouette: (h, w) bool, the posed template seen by the camera.
        mask: (h, w) bool, the capture's mask.
    """

    camera: int
    index: int
    image: np.ndarray
    iou: float
    silhouette: np.ndarray
    mask: np.ndarray


class SubjectView:
    """A parsed capture as the viewer sees it (thread-safe; :meth:`close` releases the frame sources).

    Args:
        subject: the parsed capture.
        max_side: longest side of the overlays in pixels.
        tolerance_px: silhouette edge band left out of the IoU (as ``CheckConfig.tolerance_px``).
    """

    def __init__(self, subject: Subject, max_side: int = 512, tolerance_px: int = 1):
        self.subject, self.max_side, self.tolerance_px = subject, max_side, tolerance_px
        self.template = build_template(subject.template, dtype=torch.float64)
        self.faces = self.template.faces.numpy().astype(np.int64)
        self.timeline: list[tuple[str, int]] = []
        for name, seq in subject.sequences.items():
            if seq.poses is None:
                logger.info("view: sequence %s has tracked meshes only; not on the timeline", name)
                continue
            self.timeline += [(name, int(f)) for f in np.intersect1d(seq.poses.frames, seq.frames)]
        if not self.timeline:
            raise ValueError(f"{subject.root}: no sequence with pose parameters to show")
        self.cameras = subject.cameras
        self.test_cameras = tuple(int(c) for c in subject.test_cameras)
        self._lock = threading.Lock()
        self._sources: dict[str, object] = {}
        self._verts: OrderedDict[int, np.ndarray] = OrderedDict()

    @property
    def num_frames(self) -> int:
        return len(self.timeline)

    def label(self, index: int) -> str:
        name, frame = self.timeline[index]
        return f"{name} {frame}" if len(self.subject.sequences) > 1 else str(frame)

    def camera_label(self, cam: int) -> str:
        return f"{cam}: {self.cameras[cam].name}{' (test)' if cam in self.test_cameras else ''}"

    def _index(self, index: int) -> int:
        return int(np.clip(index, 0, self.num_frames - 1))

    def posed(self, index: int) -> np.ndarray:
        """(V, 3) float64 mm, the template posed for timeline position ``index`` (cached)."""
        index = self._index(index)
        with self._lock:
            if index in self._verts:
                self._verts.move_to_end(index)
                return self._verts[index]
        name, frame = self.timeline[index]
        verts = posed_surface(self.template, self.subject.sequences[name].poses, frame)
        with self._lock:
            self._verts[index] = verts
            while len(self._verts) > _CACHED_FRAMES:
                self._verts.popitem(last=False)
        return verts

    def frame_image(self, index: int, cam: int, max_side: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The camera's (h, w, 3) uint8 image and (h, w) bool mask at ``index``, longest side ``max_side``."""
        name, frame = self.timeline[self._index(index)]
        with self._lock:  # frame sources (video decoders) are not thread-safe
            src = self._sources.get(name)
            if src is None:
                src = self._sources[name] = self.subject.sequences[name].images.open()
            rgb, mask = src.read(frame, cam)
        return scaled_view(rgb, mask, scaled_camera(self.cameras[cam], max_side or self.max_side))

    def overlay(self, index: int, cam: int) -> CameraOverlay:
        """The check's picture of camera ``cam`` at ``index`` and its IoU (at ``max_side``)."""
        index = self._index(index)
        camera = scaled_camera(self.cameras[cam], self.max_side)
        rgb, mask = self.frame_image(index, cam)
        sil = silhouettes(self.posed(index), self.faces, [camera])[0]
        return CameraOverlay(cam, index, overlay(rgb, sil, mask), mask_iou(sil, mask, self.tolerance_px), sil, mask)

    def up_direction(self) -> np.ndarray:
        """The world's up, as the cameras hold it (image y is down): the mean of their -y axes (unit), snapped
        to the nearest world axis when within about 25 degrees of it (cameras tilted down lean the mean)."""
        up = -np.mean([c.R[1] for c in self.cameras], axis=0)
        n = float(np.linalg.norm(up))
        if n < 1e-6:
            return np.array([0.0, 1.0, 0.0])
        up = up / n
        axis = int(np.argmax(np.abs(up)))
        if abs(up[axis]) > 0.9:
            up = np.sign(up[axis]) * np.eye(3)[axis]
        return up

    def close(self) -> None:
        with self._lock:
            for src in self._sources.values():
                src.close()
            self._sources.clear()


class _SubjectViewer:
    """The GUI of a capture viewer: one camera menu and timeline; per client its capture camera."""

    def __init__(self, cfg: SubjectViewConfig, view: SubjectView, server):

        self.cfg, self.view, self.server = cfg, view, server
        self._pose_of, self._mm = capture_camera_pose, MM_PER_UNIT
        self.inside: dict[int, CaptureHold] = {}  # client id -> the capture camera it looks through
        self.leaving: dict[int, tuple] = {}  # client id -> (client, the hold it moved away from) since the last tick
        self.update_lock = threading.Lock()
        gui = server.gui
        with gui.add_folder("Camera"):
            self.camera_menu = gui.add_dropdown("capture camera", [_FREE] + [view.camera_label(c) for c in
                                                                             range(len(view.cameras))],
                                                initial_value=_FREE, hint="look through a capture camera: its image "
                                                "with the template's silhouette (green) and the mask edge (red)")
            self.iou = gui.add_text("IoU", "", disabled=True, hint="silhouette vs mask, as deliffas check scores it")
            self.show_frustums = gui.add_checkbox("show cameras", True)
            self.show_mesh = gui.add_checkbox("template mesh", True)
        with gui.add_folder("Timeline"):
            self.frame = gui.add_slider("frame", 0, max(view.num_frames - 1, 1), 1, 0, disabled=view.num_frames < 2)
            self.frame_label = gui.add_text("capture frame", view.label(0), disabled=True)
            self.playing = gui.add_checkbox("play", False)
            self.speed = gui.add_slider("speed (frames/s)", 1.0, 30.0, 1.0, 5.0)

        @self.camera_menu.on_update
        def _(event) -> None:
            if self.camera_menu.value == _FREE:
                return
            cam = int(self.camera_menu.value.split(":", 1)[0])
            clients = [event.client] if event.client is not None else list(self.server.get_clients().values())
            for client in clients:
                self.goto(client, cam)

        self.frame.on_update(lambda _event: self.show_frame())
        self.show_frustums.on_update(lambda _event: self._visibility())
        self.show_mesh.on_update(lambda _event: self._visibility())
        self._build_scene()

    def _build_scene(self) -> None:
        v, scene = self.view, self.server.scene
        scene.set_up_direction(tuple(float(x) for x in v.up_direction()))
        self.frustums = {}
        for c, cam in enumerate(v.cameras):
            wxyz, position, fov = self._pose_of(cam)
            h = scene.add_camera_frustum(f"/cameras/{c}", fov, cam.width / cam.height, scale=0.12,
                                         color=(230, 60, 60) if c in v.test_cameras else (60, 60, 230),
                                         wxyz=wxyz, position=position)
            h.on_click(lambda event, c=c: self.goto(event.client, c))
            self.frustums[c] = h
        self.mesh = None
        self.show_frame()
        _, position, fov = self._pose_of(v.cameras[0])
        centre = self._centre()
        init = self.server.initial_camera  # behind camera 0, so that its frustum and the others are in view
        init.position, init.look_at, init.fov = centre + 1.6 * (position - centre), centre, fov

    def _centre(self) -> np.ndarray:
        return self.view.posed(int(self.frame.value)).mean(0) / self._mm

    def show_frame(self) -> None:
        """Pose the mesh, texture the frustums and redraw the overlays of the clients at a capture camera."""
        index = int(self.frame.value)
        with self.update_lock:
            self.frame_label.value = self.view.label(index)
            self.mesh = self.server.scene.add_mesh_simple(
                "/template", self.view.posed(index) / self._mm, self.view.faces, color=(200, 170, 140),
                side="double", visible=self._mesh_visible())
            for c, h in self.frustums.items():
                h.image = self.view.frame_image(index, c, self.cfg.texture_resolution)[0]
        for client_id, hold in list(self.inside.items()):
            client = self.server.get_clients().get(client_id)
            if client is not None:
                self._background(client, hold.camera)

    def _mesh_visible(self) -> bool:
        return bool(self.show_mesh.value) and not self.inside  # the overlay shows the silhouette already

    def _visibility(self) -> None:
        looking = {hold.camera for hold in list(self.inside.values())}
        for c, h in self.frustums.items():
            h.visible = bool(self.show_frustums.value) and c not in looking
        if self.mesh is not None:
            self.mesh.visible = self._mesh_visible()

    def goto(self, client, cam: int) -> None:
        """Move ``client``'s view to capture camera ``cam`` and show its overlay as the background."""
        camera = self.view.cameras[cam]
        wxyz, position, fov = self._pose_of(camera)
        self.inside[client.client_id] = CaptureHold.sent(cam, wxyz, position)
        self._visibility()
        with client.atomic():
            client.camera.fov = fov
            client.camera.position = position
            client.camera.look_at = position + camera.R[2] * max(
                float(np.linalg.norm(self._centre() - position)), 0.1)
            client.camera.wxyz = wxyz
        self._background(client, cam)

    def _background(self, client, cam: int) -> None:

        result = self.view.overlay(int(self.frame.value), cam)
        canvas = (int(client.camera.image_width), int(client.camera.image_height))
        client.scene.set_background_image(compose_panels([result.image], canvas if min(canvas) > 0 else None),
                                          format="png")
        self.iou.value = (f"{result.iou:.3f} ({self.view.cameras[cam].name}, frame "
                          f"{self.view.label(result.index)})")

    def moved(self, client) -> None:
        """Note a camera update that leaves the capture camera (judged on the camera as reported, see
        :class:`CaptureHold`); :meth:`tick` turns the client into a free camera."""
        hold = self.inside.get(client.client_id)
        if hold is not None and hold.left(client.camera.wxyz, client.camera.position, time.perf_counter()):
            self.leaving[client.client_id] = (client, hold)

    def tick(self) -> None:
        """A client that moved away from the capture camera it looked through becomes a free camera (no background)."""
        for client_id, (client, hold) in list(self.leaving.items()):
            self.leaving.pop(client_id, None)
            if self.inside.get(client_id) is hold:  # not a camera chosen since
                self._leave(client)

    def _leave(self, client) -> None:
        self.inside.pop(client.client_id, None)
        client.scene.set_background_image(None)
        self._visibility()
        self.camera_menu.value = _FREE  # choosing the same camera again moves back to it

    def disconnect(self, client) -> None:
        log_departure(client)
        self.leaving.pop(client.client_id, None)
        if self.inside.pop(client.client_id, None) is not None:
            self._visibility()


def serve_subject(cfg: SubjectViewConfig, stop: threading.Event | None = None,
                  ready: Callable[[], None] | None = None) -> None:
    """Serve the capture viewer at ``cfg.host:cfg.port`` until interrupted (or ``stop`` is set); ``ready`` is
    called once the capture is read and the server listens."""

    viser, _ = import_viser()
    if cfg.exposed:
        logger.warning("deliffas view: listening on %s: anyone who can reach this machine can see the viewer "
                       "(no authentication); prefer 127.0.0.1 and SSH port forwarding", cfg.host)
    try:
        subject = parse_subject(cfg.subject, cfg.format, SubjectOptions(template=cfg.template, motions=cfg.motions))
    except ValueError as err:
        if cfg.format != "auto":
            raise
        raise ValueError(f"not a run (no train_config.json) and {err}") from err
    view = SubjectView(subject, cfg.max_resolution, cfg.tolerance_px)
    server = viser.ViserServer(host=cfg.host, port=cfg.port, label="deliffas view", verbose=False)
    with departures_quiet():
        try:
            viewer = _SubjectViewer(cfg, view, server)
            server.on_client_connect(lambda client: client.camera.on_update(lambda _c: viewer.moved(client)))
            server.on_client_disconnect(viewer.disconnect)
            logger.info("deliffas view: capture %s at http://%s:%d (%d cameras, %d frames)", subject.root, cfg.host,
                        cfg.port, len(view.cameras), view.num_frames)
            if ready is not None:
                ready()
            next_frame = time.perf_counter()
            while stop is None or not stop.is_set():
                time.sleep(_TICK_S)
                viewer.tick()
                if viewer.playing.value and view.num_frames > 1 and time.perf_counter() >= next_frame:
                    viewer.frame.value = (int(viewer.frame.value) + 1) % view.num_frames
                    next_frame = time.perf_counter() + 1.0 / max(float(viewer.speed.value), 1e-3)
        finally:
            server.stop()
            view.close()
