"""SMPL model files (``.npz``, or ``.pkl`` through a restricted unpickler) read into plain arrays.

The model file layout is the official one: ``v_template`` (V, 3), ``shapedirs`` (V, 3, >= num_betas),
``posedirs`` (V, 3, 207), ``J_regressor`` (24, V) dense or scipy-sparse, ``weights`` (V, 24),
``kintree_table`` (2, 24), ``f`` (F, 3). ``.pkl`` files are read with ``safe_pickle``, which only
constructs numpy arrays (from checked arguments) and scipy sparse matrices (never arbitrary code); the official chumpy pickles
are refused with a hint to convert them to ``.npz``. Units stay the file's (metres for SMPL).
:func:`write_smpl_model` writes the same layout as ``.npz`` (atomically), so a model deliffas makes
loads through the same reader as a user's file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from jaxtyping import Float, Integer

from deliffas.io.infra.reader_checks import CaptureFormatError, read_npz, require_numbers
from deliffas.io.infra.files import durable_replace, temp_path
from deliffas.io.infra.safe_pickle import UnsafePickleError, load_numpy_pickle

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


_ALLOWED_SPARSE = {"csc_matrix", "csr_matrix", "coo_matrix", "csc_array", "csr_array", "coo_array"}


def _pickle_class(module: str, name: str) -> type | str | None:
    """The scipy sparse classes an SMPL pickle may hold; a hint for chumpy pickles."""
    if module.split(".")[0] == "chumpy":
        return (f"the pickle holds chumpy objects ({module}.{name}); deliffas does not import chumpy. "
                "Convert the model to .npz in an environment with chumpy, e.g. "
                "np.savez(out, **{k: np.asarray(v.r if hasattr(v, 'r') else v) for k, v in pkl.items()}) "
                "(J_regressor via .toarray()).")
    if module.startswith("scipy.sparse") and name in _ALLOWED_SPARSE:
        import scipy.sparse as sp

        return getattr(sp, name)
    return (f"refusing to load '{module}.{name}' from a pickle; only numpy arrays and scipy sparse matrices are "
            "allowed (convert the model to .npz)")


def _restricted_pickle_load(path: Path) -> dict:
    try:
        obj = load_numpy_pickle(path.read_bytes(), _pickle_class)
    except UnsafePickleError as err:
        raise SMPLModelError(f"{path}: {err}") from None
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


def _checked_sparse(x):
    """``x`` after scipy's full consistency check: an unpickled matrix with indices outside its shape would make
    ``toarray`` write out of bounds (fuzzing crashed the process through it)."""
    import scipy.sparse as sp

    if x.format in ("csr", "csc"):
        x.check_format(full_check=True)
    else:
        x = sp.coo_matrix(x)
        x._check()
        rows, cols = np.asarray(x.row), np.asarray(x.col)
        if rows.size and (rows.min() < 0 or rows.max() >= x.shape[0] or cols.min() < 0 or cols.max() >= x.shape[1]):
            raise ValueError("indices outside the matrix")
    return x


def _dense(path: Path, key: str, x) -> np.ndarray:
    """``x`` (an array or a scipy sparse matrix) as a float64 array of real numbers."""
    import scipy.sparse as sp

    try:
        return require_numbers(path, key, _checked_sparse(x).toarray() if sp.issparse(x) else x)
    except CaptureFormatError as err:
        raise SMPLModelError(f"{path}: '{key}' {err.expectation}") from None
    except Exception as err:  # a sparse matrix unpickled with inconsistent parts
        raise SMPLModelError(f"{path}: '{key}' is not a usable array ({type(err).__name__}: {str(err)[:120]})") from None


def load_smpl_model(path: str | os.PathLike) -> SMPLModelData:
    """Read an SMPL ``.npz`` or ``.pkl`` (restricted unpickler) and check every array's shape.

    Raises:
        FileNotFoundError: the file does not exist (the message says SMPL is not shipped and where to get it).
        SMPLModelError: a damaged file, a missing key, a wrong shape, an invalid kinematic tree, or pickle
            content that is not allowed (a class other than numpy arrays and scipy sparse matrices).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"SMPL model file not found: {p}. {SMPL_NOT_SHIPPED}")
    suffix = p.suffix.lower()
    if suffix == ".npz":
        try:
            raw = read_npz(p)
        except CaptureFormatError as err:
            raise SMPLModelError(f"{p}: '{err.key}' {err.expectation}") from None
    elif suffix in (".pkl", ".pickle"):
        raw = _restricted_pickle_load(p)
    else:
        raise SMPLModelError(f"{p}: expected an .npz or .pkl SMPL model, got '{p.suffix}'")
    missing = [k for k in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")
               if k not in raw]
    if missing:
        raise SMPLModelError(f"{p}: missing arrays {missing} (have {sorted(map(str, raw))[:12]})")
    v = _dense(p, "v_template", raw["v_template"])
    V = v.shape[0] if v.ndim == 2 else -1
    expect = {"v_template": (V, 3), "J_regressor": (NUM_JOINTS, V), "weights": (V, NUM_JOINTS),
              "kintree_table": (2, NUM_JOINTS)}
    keys = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")
    arrays = {k: _dense(p, k, raw[k]) for k in keys}
    for k, a in arrays.items():
        if not np.isfinite(a).all():
            raise SMPLModelError(f"{p}: '{k}' holds NaN or inf")
    for k, shape in expect.items():
        if arrays[k].shape != shape:
            raise SMPLModelError(f"{p}: '{k}' expected shape {shape}, got {arrays[k].shape}")
    sd = arrays["shapedirs"]
    if sd.ndim != 3 or sd.shape[:2] != (V, 3) or sd.shape[2] < 1:
        raise SMPLModelError(f"{p}: 'shapedirs' expected shape ({V}, 3, NB >= 1), got {sd.shape}")
    pd = arrays["posedirs"]
    if pd.shape != (V, 3, NUM_POSE_BASIS):
        raise SMPLModelError(f"{p}: 'posedirs' expected shape ({V}, 3, {NUM_POSE_BASIS}), got {pd.shape}")
    f = _dense(p, "f", raw["f"])
    if (f.ndim != 2 or f.shape[1] != 3 or not np.isfinite(f).all() or np.any(f != np.round(f))
            or f.min(initial=0) < 0 or f.max(initial=0) >= V):
        raise SMPLModelError(f"{p}: 'f' expected (F, 3) integer indices in [0, {V}), got shape {f.shape}")
    faces = f.astype(np.int64)
    parents = arrays["kintree_table"][0].astype(np.int64)
    parents[(parents < 0) | (parents >= NUM_JOINTS)] = -1  # the root's parent is stored as 2^32 - 1
    if parents[0] != -1 or not all(0 <= parents[j] < j for j in range(1, NUM_JOINTS)):
        raise SMPLModelError(f"{p}: 'kintree_table' must have the root first and every parent before its child")
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
