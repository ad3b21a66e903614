"""The body a synthetic capture is rendered from: a DDC character or an SMPL model, behind one record.

:func:`make_synth_body` puts the body's files into the subject (``character/`` for a DDC character,
``body/`` for an SMPL model file and its uv OBJ) and returns a :class:`SynthBody`: the template spec,
the rest mesh with its uvs, the garment region, the texture, and how the body's motions are made
(procedural, or read from a file) and written (in the template kind's own motion format).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from deliffas.io.formats.dynacap.character import read_character, write_character
from deliffas.io.motion import Motion
from deliffas.io.body_models.smpl import load_smpl_model
from deliffas.geometry.motion_gen import procedural_motion
from deliffas.geometry.procedural import ProceduralConfig, make_procedural_character
from deliffas.geometry.smpl_body import make_procedural_smpl
from deliffas.geometry.smpl_motion import procedural_smpl_motion
from deliffas.geometry.smpl_params import smpl_to_motion
from deliffas.geometry.templates import TemplateSpec, build_template, ddc_spec, smpl_spec, template_kind
from deliffas.data.garment import ddc_garment_region, smpl_garment_region
from deliffas.data.pose_motions import read_pose_motion

__all__ = ["SynthBody", "make_synth_body", "PROCEDURAL", "SMPL_NUM_BETAS"]

PROCEDURAL = "procedural"
"""``body_model`` value naming the license-free procedural body in SMPL layout."""
SMPL_NUM_BETAS = 10
"""Shape coefficients of the synthetic captures' SMPL template."""


@dataclass(frozen=True)
class SynthBody:
    """A body placed into a subject folder, ready to pose and render.

    Attributes:
        path: the body's main file inside the subject (``.character`` or SMPL ``.npz``).
        spec: the template spec the subject records (``build_template(spec)`` poses it, mm).
        faces: (F, 3) int64; uvs: (T, 2) float64; face_uvs: (F, 3) int64.
        rest_verts: (V, 3) float64 rest mesh, mm.
        garment: (V,) bool loose-garment region.
        texture: (Ht, Wt, 3) float32 albedo in [0, 1].
        rest_dofs: (D,) pose parameters of the rest pose (procedural motions start near it).
        procedural: ``(num_frames, seed, fps) -> Motion``: a procedural motion of this body.
    """

    path: Path
    spec: TemplateSpec
    faces: np.ndarray
    uvs: np.ndarray
    face_uvs: np.ndarray
    rest_verts: np.ndarray
    garment: np.ndarray
    texture: np.ndarray
    rest_dofs: np.ndarray
    procedural: Callable[[int, int, float], Motion]

    @property
    def kind(self) -> str:
        """The template kind (``ddc``, ``smpl``)."""
        return self.spec.kind

    @property
    def motion_name(self) -> str:
        """File name of a sequence's motion: ``poses`` + the template kind's motion suffix."""
        return "poses" + template_kind(self.kind).motion_suffix

    def motion(self, path: str | None, num_frames: int, seed: int, fps: float) -> Motion:
        """``num_frames`` frames (numbered 0..N-1) of pose parameters: from ``path`` or procedural."""
        if path is not None:
            m = read_pose_motion(path, self.spec, num_dofs=len(self.rest_dofs))
            if m.num_frames < num_frames:
                raise ValueError(f"{path}: has {m.num_frames} frames, {num_frames} requested")
            return Motion(np.arange(num_frames, dtype=np.int64), m.dofs[:num_frames].copy())
        return self.procedural(num_frames, seed, fps)

    def write_motion(self, seq_dir: Path, motion: Motion, fps: float) -> Path:
        """Write a sequence's pose parameters in the body's own motion format; returns the file."""
        path = seq_dir / self.motion_name
        template_kind(self.kind).write_motion(path, motion, fps)
        return path


def _texture(texture_path: Path | None, seed: int) -> np.ndarray:
    """(Ht, Wt, 3) float32 texture from a file, or a seeded procedural one."""
    if texture_path is not None:
        img = cv2.imread(str(texture_path), cv2.IMREAD_COLOR)
        if img is not None:
            return cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    rng = np.random.default_rng(seed)
    size = 256
    yy, xx = np.mgrid[0:size, 0:size] / size
    base = rng.uniform(0.3, 0.8, 3)
    checker = ((np.floor(xx * 16) + np.floor(yy * 16)) % 2)[..., None]
    noise = cv2.GaussianBlur(rng.uniform(0, 1, (size, size, 3)).astype(np.float32), (0, 0), 3)
    return np.clip(base * (0.75 + 0.25 * checker) + 0.3 * (noise - 0.5), 0, 1).astype(np.float32)


def _ddc_body(out: Path, character: str | None, seed: int, skinning: str) -> SynthBody:
    if character is not None:
        source = read_character(character)
        path = write_character(out / "character", source, name=Path(character).stem)
    else:
        path = Path(make_procedural_character(ProceduralConfig(out / "character", seed=seed)))
    c = read_character(path)
    if c.mesh.face_uvs is None:
        raise ValueError(f"{c.files.mesh}: the character has no per-corner uvs (vt); a synthetic capture needs them")
    rest_dofs = np.asarray(c.rest_dofs, np.float64)

    def procedural(num_frames: int, seed: int, fps: float) -> Motion:
        m = procedural_motion(c.skeleton, num_frames, seed, style="mixed", rest_dofs=rest_dofs, fps=fps)
        return Motion(np.arange(m.num_frames, dtype=np.int64), np.asarray(m.dofs, np.float64))

    return SynthBody(path, ddc_spec(path, skinning), np.asarray(c.mesh.faces, np.int64),
                     np.asarray(c.mesh.uvs, np.float64), np.asarray(c.mesh.face_uvs, np.int64),
                     np.asarray(c.mesh.verts, np.float64), ddc_garment_region(c), _texture(c.texture, seed),
                     rest_dofs, procedural)


def _smpl_body(out: Path, model: str, uv_obj: str | None, seed: int) -> SynthBody:
    body_dir = out / "body"
    body_dir.mkdir(parents=True, exist_ok=True)
    if model == PROCEDURAL:
        path = make_procedural_smpl(body_dir, seed)
        uv_path = path.with_name("smpl_procedural_uv.obj")
    else:
        path = body_dir / Path(model).name
        shutil.copyfile(model, path)
        uv_path = None
        if uv_obj is not None:
            uv_path = body_dir / Path(uv_obj).name
            shutil.copyfile(uv_obj, uv_path)
    spec = smpl_spec(path, uv_path, num_betas=SMPL_NUM_BETAS)
    template = build_template(spec)
    data = load_smpl_model(path)
    rest = template.rest_verts.numpy().astype(np.float64)
    return SynthBody(path, spec, template.faces.numpy(), template.uvs.numpy().astype(np.float64),
                     template.face_uvs.numpy(), rest, smpl_garment_region(rest, data.weights), _texture(None, seed),
                     np.zeros(template.num_dofs),
                     lambda num_frames, seed, fps: smpl_to_motion(procedural_smpl_motion(num_frames, seed, fps),
                                                                  SMPL_NUM_BETAS))


def make_synth_body(out: Path, seed: int, character: str | None = None, body_model: str | None = None,
                    body_uv: str | None = None, skinning: str = "dqs") -> SynthBody:
    """Put the body into the subject folder ``out`` and describe it.

    Args:
        character: a ``.character`` to copy (default: the procedural DDC character), when no ``body_model``.
        body_model: an SMPL model file (``.npz``/``.pkl``) or ``"procedural"`` (the license-free body in
            SMPL layout); ``body_uv``: an OBJ with its uv layout (else xatlas makes one).
    """
    if body_model is not None:
        if character is not None:
            raise ValueError("give a DDC character or an SMPL body model, not both")
        return _smpl_body(out, body_model, body_uv, seed)
    return _ddc_body(out, character, seed, skinning)
