"""Skeletool ``.skeleton`` files: joints, markers, scaling joints and DOFs (formats doc 1.3) as typed records."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from jaxtyping import Float, Integer

from deliffas.io.infra.text_lines import DynaCapFormatError, TextLines, write_text_atomic

__all__ = ["Joint", "Marker", "Dof", "Skeleton", "read_skeleton", "write_skeleton", "SKELETON_HEADER", "JointType"]

PathLike = str | os.PathLike
JointType = Literal["revolute", "prismatic"]

SKELETON_HEADER = "Skeletool Skeleton Definition V1.0"


@dataclass(frozen=True)
class Joint:
    """One skeleton joint (a line of the ``joints:`` section).

    Attributes:
        offset: (3,) translation from the parent frame, mm, in the parent frame (before ``scale``).
        axis: (3,) rotation axis (revolute; normalised by forward kinematics) or translation direction
            (prismatic; used as written, like the C++ reader). Kept as in the file for exact round trips.
    """

    name: str
    type: JointType
    parent: str
    offset: Float[np.ndarray, "3"]
    axis: Float[np.ndarray, "3"]
    scale: float = 1.0


@dataclass(frozen=True)
class Marker:
    """A skeleton marker; kept for round trips, unused by deliffas."""

    name: str
    parent: str
    type: str
    values: tuple[float, ...]


@dataclass(frozen=True)
class Dof:
    """A degree of freedom: joint parameters += weight * DOF value for each (joint, weight)."""

    name: str
    limits: tuple[float, float] | None
    joints: tuple[tuple[str, float], ...]


@dataclass(frozen=True)
class Skeleton:
    """A Skeletool V1.0 skeleton: joints (file order), markers, scaling groups and DOFs (motion column order)."""

    joints: tuple[Joint, ...]
    markers: tuple[Marker, ...] = ()
    scaling_joints: tuple[tuple[str, tuple[str, ...]], ...] = ()
    dofs: tuple[Dof, ...] = ()
    trailer: tuple[str, ...] = ("textureEntries: 0",)

    @property
    def num_joints(self) -> int:
        return len(self.joints)

    @property
    def num_dofs(self) -> int:
        return len(self.dofs)

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    def joint_index(self, name: str, match: Literal["exact", "prefix"] = "exact") -> int:
        """Index of a joint by name.

        ``exact`` matches the whole name; ``prefix`` returns the first joint whose name starts with
        ``name``, as the original C++ ``getJointByName`` does (formats doc 1.3). Raises KeyError.
        """
        for i, j in enumerate(self.joints):
            if j.name == name or (match == "prefix" and j.name.startswith(name)):
                return i
        raise KeyError(name)

    def bone_joint_index(self, bone: str) -> int:
        """Joint that carries a skin bone: the *last* joint whose name starts with the bone name.

        This is the C++ rule (``getLastJointByName``) the original tools and DynaCap data used;
        it differs from the PyTorch port for the forearm and foot bones (formats doc 1.5).
        """
        for i in range(self.num_joints - 1, -1, -1):
            if self.joints[i].name.startswith(bone):
                return i
        raise KeyError(bone)

    def parent_indices(self) -> Integer[np.ndarray, "J"]:
        """(J,) int64 parent index of every joint, -1 for the root."""
        index = {j.name: i for i, j in enumerate(self.joints)}
        return np.array([index.get(j.parent, -1) for j in self.joints], dtype=np.int64)

    def dof_weights(self, match: Literal["exact", "prefix"] = "prefix") -> Float[np.ndarray, "D J"]:
        """(D, J) float64 matrix W with joint parameters p = x @ W for DOF values x (D,).

        ``prefix`` (default) resolves DOF joint references like the original tools; the two rules
        differ only for the finger flex1 DOFs of the DDC skeleton (formats doc 1.3).
        """
        W = np.zeros((self.num_dofs, self.num_joints))
        for d, dof in enumerate(self.dofs):
            for name, weight in dof.joints:
                W[d, self.joint_index(name, match)] += weight
        return W


def read_skeleton(path: PathLike) -> Skeleton:
    """Read a ``Skeletool Skeleton Definition V1.0`` file (formats doc 1.3)."""
    t = TextLines(path, what="skeleton file")
    t.header((SKELETON_HEADER,))
    n = _count_line(t, "joints:")
    joints = []
    names: set[str] = set()
    for _ in range(n):
        toks = t.tokens("a joint line 'name type parent ox oy oz ax ay az scale'", 10)
        name, jtype, parent = toks[:3]
        if jtype not in ("revolute", "prismatic"):
            raise t.error(f"expected joint type 'revolute' or 'prismatic', got '{jtype}'")
        if name in names:
            raise t.error(f"duplicate joint name '{name}'")
        names.add(name)
        vals = t.floats(toks[3:], f"joint '{name}'")
        axis = np.array(vals[3:6])
        if jtype == "revolute" and np.linalg.norm(axis) < 1e-12:
            raise t.error(f"revolute joint '{name}' has a zero rotation axis")
        joints.append(Joint(name, jtype, parent, np.array(vals[:3]), axis, vals[6]))
    roots = [j.name for j in joints if j.parent not in names]
    if len(roots) != 1:
        raise DynaCapFormatError(t.path, 0, f"expected exactly one root joint (a parent name that matches no joint), got {len(roots)}: {roots[:5]}")
    _check_acyclic(t.path, joints)
    m = _count_line(t, "markers:")
    markers = []
    for _ in range(m):
        toks = t.tokens("a marker line 'name parent type x y z ...'", (6, 7, 10, 11))
        markers.append(Marker(toks[0], toks[1], toks[2], tuple(t.floats(toks[3:], f"marker '{toks[0]}'"))))
    s = _count_line(t, "scaling joints:")
    scaling = []
    for _ in range(s):
        toks = t.tokens("a scaling group line 'name n'", 2)
        k = t.to_int(toks[1], "scaling group size")
        members = tuple(t.tokens("a scaling joint name", 1)[0] for _ in range(k))
        scaling.append((toks[0], members))
    d = _count_line(t, "dofs:")
    dofs = []
    for _ in range(d):
        toks = t.tokens("a DOF line 'name n'", 2)
        dname, k = toks[0], t.to_int(toks[1], "DOF joint count")
        if k < 0 or k > t.remaining:
            raise t.error(f"DOF '{dname}' joint count {k} is negative or exceeds the lines left")
        lim = t.tokens("'limits lo hi' or 'nolimits'", (1, 3))
        if lim[0] == "nolimits" and len(lim) == 1:
            limits = None
        elif lim[0] == "limits" and len(lim) == 3:
            lo, hi = t.floats(lim[1:], f"DOF '{dname}' limits")
            limits = (lo, hi)
        else:
            raise t.error(f"expected 'limits lo hi' or 'nolimits' for DOF '{dname}', got '{' '.join(lim)[:60]}'")
        refs = []
        for _ in range(k):
            jt = t.tokens(f"'joint weight' for DOF '{dname}'", 2)
            if not any(nm == jt[0] or nm.startswith(jt[0]) for nm in names):
                raise t.error(f"DOF '{dname}' refers to unknown joint '{jt[0]}'")
            refs.append((jt[0], t.to_float(jt[1], f"DOF '{dname}' weight")))
        dofs.append(Dof(dname, limits, tuple(refs)))
    trailer = []
    while not t.at_end():
        trailer.append(t.next("trailer"))
    return Skeleton(tuple(joints), tuple(markers), tuple(scaling), tuple(dofs), tuple(trailer))


def _count_line(t: TextLines, keyword: str) -> int:
    toks = t.tokens(f"'{keyword} N'")
    word = " ".join(toks[:-1])
    if word != keyword or len(toks) < 2:
        raise t.error(f"expected '{keyword} N', got '{' '.join(toks)[:60]}'")
    n = t.to_int(toks[-1], f"'{keyword}' count")
    if n < 0 or n > t.remaining:
        raise t.error(f"'{keyword}' count {n} is negative or exceeds the {t.remaining} lines left (truncated file?)")
    return n


def _check_acyclic(path: Path, joints: list[Joint]) -> None:
    parent = {j.name: j.parent for j in joints}
    for j in joints:
        seen, cur = set(), j.name
        while cur in parent:
            if cur in seen:
                raise DynaCapFormatError(path, 0, f"joint hierarchy has a cycle through '{cur}'")
            seen.add(cur)
            cur = parent[cur]


def write_skeleton(path: PathLike, skel: Skeleton, crlf: bool = False) -> None:
    """Write a skeleton in the V1.0 layout (column-aligned like the original files)."""
    out = [SKELETON_HEADER, f"joints: {skel.num_joints}"]
    for j in skel.joints:
        nums = " ".join(f"{float(v)!r:>10}" for v in (*j.offset, *j.axis))
        out.append(f"  {j.name:<20} {j.type:<9} {j.parent:<25} {nums} {j.scale!r:>10}")
    out.append(f"markers: {len(skel.markers)}")
    for m in skel.markers:
        out.append(f"  {m.name:<20} {m.parent:<20} {m.type:<6} " + " ".join(f"{float(v)!r:>10}" for v in m.values))
    out.append(f"scaling joints: {len(skel.scaling_joints)}")
    for name, members in skel.scaling_joints:
        out.append(f"  {name} {len(members)}")
        out.extend(f"      {m}" for m in members)
    out.append(f"dofs: {skel.num_dofs}")
    for d in skel.dofs:
        out.append(f"  {d.name:<20} {len(d.joints)}")
        out.append("      nolimits" if d.limits is None else f"      limits {d.limits[0]!r} {d.limits[1]!r}")
        out.extend(f"      {name:<26} {w!r}" for name, w in d.joints)
    out.extend(skel.trailer)
    write_text_atomic(path, "\n".join(out) + "\n", crlf)


