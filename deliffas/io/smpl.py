"""SMPL model files (``.npz``, or ``.pkl`` through a restricted unpickler) read into plain arrays.

The model file layout is the official one: ``v_template`` (V, 3), ``shapedirs`` (V, 3, >= num_betas),
``posedirs`` (V, 3, 207), ``J_regressor`` (24, V) dense or scipy-sparse, ``weights`` (V, 24),
``kintree_table`` (2, 24), ``f`` (F, 3). ``.pkl`` files are read with a restricted unpickler that only
constructs numpy arrays and scipy sparse matrices (never arbitrary code); the official chumpy pickles
are refused with a hint to convert them to ``.npz``. Units stay the file's (metres for SMPL).
:func:`write_smpl_model` writes the same layout as ``.npz`` (atomically), so a model deliffas makes
loads through the same reader as a user's file.
"""

from __future__ import annotations

import io
import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from jaxtyping import Float, Integer

from deliffas.io.files import durable_replace, temp_path

__all__ = ["SMPL_NOT_SHIPPED", "SMPLModelError", "SMPLModelData", "load_smpl_model", "write_smpl_model", "NUM_JOINTS",
           "NUM_POSE_BASIS"]

NUM_JOINTS = 24
NUM_POSE_BASIS = 9 * (NUM_JOINTS - 1)  # 207

SMPL_NOT_SHIPPED = (
    "SMPL is not shipped with deliffas (its license does not allow redistribution). Register and download "
    "the model at https://smpl.is.tue.mpg.de (e.g. basicmodel_neutral_lbs_10_207_0_v1.1.0.pkl), convert it "
    "to .npz without chumpy (keys v_template, shapedirs, posedirs, J_regressor, weights, kintree_table, f), "
    "and pass that file's path."
)


class SMPLModelError(ValueError):
    """An SMPL model file that cannot be used (wrong layout, refused pickle content)."""


_ALLOWED_PICKLE = {
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("copy_reg", "_reconstructor"), ("copyreg", "_reconstructor"),
    ("__builtin__", "object"), ("builtins", "object"), ("_codecs", "encode"),
}
_ALLOWED_SPARSE = {"csc_matrix", "csr_matrix", "coo_matrix", "csc_array", "csr_array", "coo_array"}


class _RestrictedUnpickler(pickle.Unpickler):
    """Only numpy arrays/dtypes/scalars and scipy sparse matrices may be constructed."""

    def find_class(self, module: str, name: str):
        if module.split(".")[0] == "chumpy":
            raise SMPLModelError(
                f"{self.path}: the pickle holds chumpy objects ({module}.{name}); deliffas does not import chumpy. "
                "Convert the model to .npz in an environment with chumpy, e.g. "
                "np.savez(out, **{k: np.asarray(v.r if hasattr(v, 'r') else v) for k, v in pkl.items()}) "
                "(J_regressor via .toarray()).")
        if (module, name) in _ALLOWED_PICKLE:
            return super().find_class(module, name)
        if module.startswith("scipy.sparse") and name in _ALLOWED_SPARSE:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(
            f"{self.path}: refusing to load '{module}.{name}' from a pickle; only numpy arrays and scipy "
            "sparse matrices are allowed (convert the model to .npz)")


def _restricted_pickle_load(path: Path) -> dict:
    with open(path, "rb") as fh:
        data = fh.read()
    unpickler = _RestrictedUnpickler(io.BytesIO(data), encoding="latin1")
    unpickler.path = path
    obj = unpickler.load()
    if not isinstance(obj, dict):
        raise SMPLModelError(f"{path}: expected a pickled dict of arrays, got {type(obj).__name__}")
    return obj


@dataclass(frozen=True)
class SMPLModelData:
    """The arrays of an SMPL model (model units: metres for the official files).

    Attributes:
        v_template: (V, 3) float64 mean template.
        shapedirs: (V, 3, NB) float64 shape blend shapes.
        posedirs: (V, 3, 207) float64 pose blend shapes.
        J_regressor: (24, V) float64 dense joint regressor.
        weights: (V, 24) float64 skinning weights.
        parents: (24,) int64 parent joint, -1 for the root (parents precede children).
        faces: (F, 3) int64.
    """

    v_template: Float[np.ndarray, "V 3"]
    shapedirs: Float[np.ndarray, "V 3 NB"]
    posedirs: Float[np.ndarray, "V 3 207"]
    J_regressor: Float[np.ndarray, "24 V"]
    weights: Float[np.ndarray, "V 24"]
    parents: Integer[np.ndarray, "24"]
    faces: Integer[np.ndarray, "F 3"]

    @property
    def num_verts(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_betas(self) -> int:
        return int(self.shapedirs.shape[2])


def _dense(x) -> np.ndarray:
    if hasattr(x, "toarray"):
        return np.asarray(x.toarray(), np.float64)
    return np.asarray(x, np.float64)


def load_smpl_model(path: str | os.PathLike) -> SMPLModelData:
    """Read an SMPL ``.npz`` or ``.pkl`` (restricted unpickler) and check every array's shape.

    Raises:
        FileNotFoundError: the file does not exist (the message says SMPL is not shipped and where to get it).
        SMPLModelError: a missing key, a wrong shape, an invalid kinematic tree or refused pickle content.
        pickle.UnpicklingError: the pickle asks for a class that is not allowed.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"SMPL model file not found: {p}. {SMPL_NOT_SHIPPED}")
    suffix = p.suffix.lower()
    if suffix == ".npz":
        with np.load(p, allow_pickle=False) as z:
            raw = {k: z[k] for k in z.files}
    elif suffix in (".pkl", ".pickle"):
        raw = _restricted_pickle_load(p)
    else:
        raise SMPLModelError(f"{p}: expected an .npz or .pkl SMPL model, got '{p.suffix}'")
    missing = [k for k in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")
               if k not in raw]
    if missing:
        raise SMPLModelError(f"{p}: missing arrays {missing} (have {sorted(raw)[:12]})")
    v = _dense(raw["v_template"])
    V = v.shape[0] if v.ndim == 2 else -1
    expect = {"v_template": (V, 3), "J_regressor": (NUM_JOINTS, V), "weights": (V, NUM_JOINTS),
              "kintree_table": (2, NUM_JOINTS)}
    keys = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
    arrays = {k: _dense(raw[k]) for k in keys}
    for k, shape in expect.items():
        if arrays[k].shape != shape:
            raise SMPLModelError(f"{p}: '{k}' expected shape {shape}, got {arrays[k].shape}")
    sd = arrays["shapedirs"]
    if sd.ndim != 3 or sd.shape[:2] != (V, 3) or sd.shape[2] < 1:
        raise SMPLModelError(f"{p}: 'shapedirs' expected shape ({V}, 3, NB >= 1), got {sd.shape}")
    pd = arrays["posedirs"]
    if pd.shape != (V, 3, NUM_POSE_BASIS):
        raise SMPLModelError(f"{p}: 'posedirs' expected shape ({V}, 3, {NUM_POSE_BASIS}), got {pd.shape}")
    faces = np.asarray(raw["f"]).astype(np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min(initial=0) < 0 or faces.max(initial=0) >= V:
        raise SMPLModelError(f"{p}: 'f' expected (F, 3) indices in [0, {V}), got shape {faces.shape}")
    parents = arrays["kintree_table"][0].astype(np.int64)
    parents[(parents < 0) | (parents >= NUM_JOINTS)] = -1  # the root's parent is stored as 2^32 - 1
    if parents[0] != -1 or not all(0 <= parents[j] < j for j in range(1, NUM_JOINTS)):
        raise SMPLModelError(f"{p}: 'kintree_table' must have the root first and every parent before its child")
    for k, a in arrays.items():
        if not np.isfinite(a).all():
            raise SMPLModelError(f"{p}: '{k}' holds NaN or inf")
    return SMPLModelData(v, sd, pd, arrays["J_regressor"], arrays["weights"], parents, faces)


ROOT_PARENT = 4294967295
"""``kintree_table[0, 0]`` in the official files (uint32 -1)."""


def write_smpl_model(path: str | os.PathLike, data: SMPLModelData) -> None:
    """Write ``data`` as an official-layout SMPL ``.npz`` that :func:`load_smpl_model` reads back equal.

    Keys: ``v_template`` (V, 3), ``shapedirs`` (V, 3, NB), ``posedirs`` (V, 3, 207), ``J_regressor``
    (24, V) dense, ``weights`` (V, 24) (all float64), ``kintree_table`` (2, 24) int64 (parents with the
    root's as 4294967295, then the joint ids), ``f`` (F, 3) uint32. Written under a temporary name
    and renamed into place.

    Raises:
        SMPLModelError: ``path`` does not end in ``.npz``.
    """
    p = Path(path)
    if p.suffix.lower() != ".npz":
        raise SMPLModelError(f"{p}: write_smpl_model writes .npz files, got '{p.suffix}'")
    parents = np.asarray(data.parents, np.int64)
    kintree = np.stack([np.where(parents < 0, ROOT_PARENT, parents), np.arange(len(parents))]).astype(np.int64)
    arrays = {"v_template": data.v_template, "shapedirs": data.shapedirs, "posedirs": data.posedirs,
              "J_regressor": data.J_regressor, "weights": data.weights}
    arrays = {k: np.asarray(v, np.float64) for k, v in arrays.items()}
    arrays["kintree_table"] = kintree
    arrays["f"] = np.asarray(data.faces).astype(np.uint32)
    tmp = temp_path(p)
    with open(tmp, "wb") as fh:  # a file object: np.savez_compressed would append .npz to a name
        np.savez_compressed(fh, **arrays)
    durable_replace(tmp, p)
