"""The ``Template`` protocol, the recorded ``TemplateSpec`` and the registry that builds one from the other.

A template kind (``ddc``, ``ddc_graph``, ``smpl``, or a user's) is one module that registers a
:class:`TemplateKind`: its builder ``(spec, dtype) -> Template`` and what else only the kind knows (its
motion files, whether its pose rows are SMPL parameters); nothing outside this registry compares kind
names. Installed packages add kinds through the ``deliffas.templates`` entry-point group. Every
deliffas command builds templates through
:func:`build_template`, so a spec recorded in a shard set (``meta.h5``), a run or an avatar file is
enough to rebuild the exact template: the spec names its source files with their sha256, and
building checks them.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Protocol, runtime_checkable

import torch
from jaxtyping import Float, Integer
from torch import Tensor

from deliffas.io.infra.files import sha256_file
from deliffas.io.motion import Motion
from deliffas.plugins import load_plugins

__all__ = [
    "Template",
    "TemplateSpec",
    "TemplateSourceError",
    "TemplateBuilder",
    "TemplateKind",
    "register_template_kind",
    "template_kind",
    "template_kinds",
    "TEMPLATES_ENTRY_POINT",
    "build_template",
    "make_spec",
]


@runtime_checkable
class Template(Protocol):
    """What the rest of deliffas needs from a template: posing plus fixed topology and uvs.

    Templates are torch modules: ``pose`` takes and returns tensors in the template's dtype and on
    its device (``deliffas.data.posing.pose_frames`` is the numpy boundary).

    Attributes:
        faces: (F, 3) int64 vertex indices.
        uvs: (T, 2) float uv coordinates in [0, 1]^2 (OBJ convention, v up).
        face_uvs: (F, 3) int64 per-corner indices into ``uvs`` (UV seams live here).
    """

    faces: Integer[Tensor, "F 3"]
    uvs: Float[Tensor, "T 2"]
    face_uvs: Integer[Tensor, "F 3"]

    @property
    def num_verts(self) -> int: ...

    @property
    def num_dofs(self) -> int:
        """D: length of one frame's pose parameters."""
        ...

    @property
    def rest_verts(self) -> Float[Tensor, "V 3"]:
        """(V, 3) vertices of the template mesh as its file has them (mm, world frame)."""
        ...

    def pose(self, dofs: Float[Tensor, "B D"]) -> Float[Tensor, "B V 3"]:
        """(B, D) pose parameters -> (B, V, 3) posed vertices, mm, world frame, template vertex order."""
        ...


class TemplateSourceError(ValueError):
    """A template spec whose source files are missing or changed since the spec was recorded."""


@dataclass(frozen=True)
class TemplateSpec:
    """A template as recorded in shards, runs and avatars: its kind, source files and options.

    Attributes:
        kind: registered template kind (``template_kinds()``): ``ddc``, ``ddc_graph``, ``smpl``, ...
        files: role -> absolute path (str) of every source file (e.g. ``character``, ``mesh``,
            ``model``, ``outer``).
        sha256: role -> hex sha256 of that file's bytes when the spec was made.
        options: kind-specific JSON values (e.g. ``skinning``: ``dqs``/``lbs``; ``num_betas``: int;
            ``scale``: model units -> mm, float).
    """

    kind: str
    files: Mapping[str, str] = field(default_factory=dict)
    sha256: Mapping[str, str] = field(default_factory=dict)
    options: Mapping[str, Any] = field(default_factory=dict)

    def path(self, role: str) -> Path:
        """The source file of ``role``; KeyError names the roles the spec has."""
        if role not in self.files:
            raise KeyError(f"template spec ({self.kind}) has no '{role}' file (has {sorted(self.files)})")
        return Path(self.files[role])

    def option(self, name: str, default: Any = None) -> Any:
        return self.options.get(name, default)

    def verify(self) -> None:
        """Raise :class:`TemplateSourceError` when a source file is missing or its bytes changed."""
        for role, path in self.files.items():
            p = Path(path)
            if not p.is_file():
                raise TemplateSourceError(f"{p}: the template's '{role}' file is gone (the {self.kind} template was "
                                          f"recorded with it)")
            expected = self.sha256.get(role)
            if expected is not None and sha256_file(p) != expected:
                raise TemplateSourceError(f"{p}: the template's '{role}' file changed since it was recorded "
                                          f"(sha256 {expected[:12]}...)")

    def to_dict(self) -> dict:
        return {"kind": self.kind, "files": dict(self.files), "sha256": dict(self.sha256),
                "options": dict(self.options)}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "TemplateSpec":
        if not isinstance(d, Mapping) or not isinstance(d.get("kind"), str):
            raise ValueError(f"template spec: expected an object with a 'kind' string, got {str(d)[:80]!r}")
        unknown = set(d) - {"kind", "files", "sha256", "options"}
        if unknown:
            raise ValueError(f"template spec: unknown keys {sorted(unknown)}")
        return cls(d["kind"], dict(d.get("files", {})), dict(d.get("sha256", {})), dict(d.get("options", {})))

    @classmethod
    def from_json(cls, text: str) -> "TemplateSpec":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as err:
            raise ValueError(f"template spec: not JSON ({err})") from None
        return cls.from_dict(d)


def make_spec(kind: str, files: Mapping[str, str | os.PathLike | None], **options: Any) -> TemplateSpec:
    """A spec of ``kind`` with the given source files (None entries dropped), hashed now.

    Paths are made absolute without resolving symbolic links: a file names its neighbours relative to the
    path it is read through (a symlinked ``.character`` reads the files beside the link), so the spec records
    and the build reads the very files that were hashed.
    """
    paths = {role: os.path.abspath(p) for role, p in files.items() if p is not None}
    for role, p in paths.items():
        if not Path(p).is_file():
            raise FileNotFoundError(f"{p}: the {kind} template's '{role}' file does not exist")
    return TemplateSpec(kind, paths, {role: sha256_file(p) for role, p in paths.items()}, dict(options))


TemplateBuilder = Callable[[TemplateSpec, torch.dtype], Template]

TEMPLATES_ENTRY_POINT = "deliffas.templates"
"""The entry-point group whose modules register template kinds when imported."""


@dataclass(frozen=True)
class TemplateKind:
    """A template kind and the facts only it knows.

    Attributes:
        name: the kind recorded in every ``TemplateSpec``.
        build: ``(spec, dtype) -> Template``.
        motion_suffix: the suffix of its motion files (``.motion``, ``.npz``), lower case; None: it has none.
        read_motion: ``(path, spec, num_dofs) -> Motion``: a motion file as the template's pose rows
            (``num_dofs``, when given, is checked against the file).
        write_motion: ``(path, motion, fps) -> None``: pose rows written as its motion file.
        smpl_params: its pose rows are SMPL parameters ``[transl (3, m), pose (72), betas]`` (captures
            with SMPL fits, SMPL exports and the SMPL checks take it).
    """

    name: str
    build: TemplateBuilder
    motion_suffix: str | None = None
    read_motion: Callable[[Path, "TemplateSpec", int | None], Motion] | None = None
    write_motion: Callable[[Path, Motion, float], None] | None = None
    smpl_params: bool = False


_KINDS: dict[str, TemplateKind] = {}


def register_template_kind(kind: TemplateKind) -> None:
    """Register a template kind (once per name)."""
    if kind.name in _KINDS:
        raise ValueError(f"template kind {kind.name!r} is registered already")
    _KINDS[kind.name] = kind


def template_kinds() -> tuple[str, ...]:
    """The registered template kinds, sorted."""
    load_plugins(TEMPLATES_ENTRY_POINT)
    return tuple(sorted(_KINDS))


def template_kind(name: str) -> TemplateKind:
    """The registered kind ``name``.

    Raises:
        ValueError: an unknown kind (the message lists those that are registered).
    """
    load_plugins(TEMPLATES_ENTRY_POINT)
    kind = _KINDS.get(name)
    if kind is None:
        raise ValueError(f"unknown template kind {name!r}; registered: {', '.join(template_kinds())}")
    return kind


def build_template(spec: TemplateSpec, dtype: torch.dtype = torch.float32, verify: bool = True) -> Template:
    """The template a spec describes.

    Args:
        spec: kind, source files and options (e.g. read back from a shard set's ``meta.h5``).
        dtype: buffer dtype (float64 for bit-level comparisons).
        verify: check the source files' sha256 against the spec first.

    Raises:
        ValueError: the kind is not registered (the message lists those that are).
        TemplateSourceError: ``verify`` and a source file is missing or changed.
    """
    kind = template_kind(spec.kind)
    if verify:
        spec.verify()
    return kind.build(spec, dtype)
