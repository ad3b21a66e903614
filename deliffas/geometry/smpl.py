"""SMPL as a ``DeformableTemplate``, from a model file the user supplies (SMPL is not shipped: license).

The model file is ``.npz`` (preferred) or ``.pkl`` with the official layout: ``v_template`` (V, 3),
``shapedirs`` (V, 3, >= num_betas), ``posedirs`` (V, 3, 207), ``J_regressor`` (24, V) dense or
scipy-sparse, ``weights`` (V, 24), ``kintree_table`` (2, 24), ``f`` (F, 3). ``.pkl`` files are read
with a restricted unpickler that only constructs numpy arrays and scipy sparse matrices (never
arbitrary code); the official chumpy pickles are refused with a hint to convert them to ``.npz``.

The maths are smplx-style plain batched functions (``batch_rodrigues``, ``blend_shapes``,
``batch_rigid_transform``, ``smpl_lbs``); ``SMPLTemplate`` only holds buffers. SMPL is in metres;
``scale=1000`` (default) puts vertices and translations in the mm world of deliffas.
"""

from __future__ import annotations

import io
import logging
import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from deliffas.checks import check_finite, check_shape

__all__ = [
    "SMPL_NOT_SHIPPED",
    "SMPLModelError",
    "SMPLModelData",
    "load_smpl_model",
    "batch_rodrigues",
    "blend_shapes",
    "batch_rigid_transform",
    "smpl_lbs",
    "SMPLTemplate",
]

log = logging.getLogger(__name__)

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


# --------------------------------------------------------------------------------------------- loading
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

    v_template: np.ndarray
    shapedirs: np.ndarray
    posedirs: np.ndarray
    J_regressor: np.ndarray
    weights: np.ndarray
    parents: np.ndarray
    faces: np.ndarray

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


# --------------------------------------------------------------------------------------------- maths
def batch_rodrigues(rot_vecs: torch.Tensor) -> torch.Tensor:
    """(N, 3) axis-angle vectors -> (N, 3, 3) rotation matrices (zero vector -> identity)."""
    angle = torch.linalg.norm(rot_vecs + 1e-8, dim=1, keepdim=True)  # (N, 1), as smplx
    axis = rot_vecs / angle
    cos, sin = torch.cos(angle)[:, :, None], torch.sin(angle)[:, :, None]
    x, y, z = axis.unbind(1)
    zeros = torch.zeros_like(x)
    K = torch.stack([zeros, -z, y, z, zeros, -x, -y, x, zeros], dim=1).reshape(-1, 3, 3)
    eye = torch.eye(3, dtype=rot_vecs.dtype, device=rot_vecs.device)[None]
    return eye + sin * K + (1 - cos) * torch.bmm(K, K)


def blend_shapes(betas: torch.Tensor, shapedirs: torch.Tensor) -> torch.Tensor:
    """(B, NB) betas, (V, 3, NB) shapedirs -> (B, V, 3) displacements."""
    return torch.einsum("bl,mkl->bmk", betas, shapedirs)


def batch_rigid_transform(rot_mats: torch.Tensor, joints: torch.Tensor,
                          parents: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Global joint transforms of a kinematic tree (parents precede children).

    Args:
        rot_mats: (B, J, 3, 3) local rotations.
        joints: (B, J, 3) rest joint locations.
        parents: (J,) long, -1 for the root.

    Returns:
        posed joints (B, J, 3) and skinning transforms (B, J, 4, 4) relative to the rest pose.
    """
    B, J = joints.shape[:2]
    rel = joints.clone()
    rel[:, 1:] -= joints[:, parents[1:]]
    local = torch.zeros(B, J, 4, 4, dtype=joints.dtype, device=joints.device)
    local[..., :3, :3] = rot_mats
    local[..., :3, 3] = rel
    local[..., 3, 3] = 1
    chain = [local[:, 0]]
    for j in range(1, J):  # a loop over the 24 joints
        chain.append(chain[int(parents[j])] @ local[:, j])
    glob = torch.stack(chain, dim=1)  # (B, J, 4, 4)
    posed_joints = glob[..., :3, 3]
    rel_T = glob.clone()
    rel_T[..., :3, 3] -= torch.einsum("bjik,bjk->bji", glob[..., :3, :3], joints)
    return posed_joints, rel_T


def smpl_lbs(betas: torch.Tensor, pose: torch.Tensor, v_template: torch.Tensor, shapedirs: torch.Tensor,
             posedirs: torch.Tensor, J_regressor: torch.Tensor, parents: torch.Tensor,
             lbs_weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """SMPL: shape blend shapes, joint regression, pose blend shapes, linear blend skinning.

    Args:
        betas: (B, NB). pose: (B, 72) axis-angle (global orientation first).
        v_template: (V, 3). shapedirs: (V, 3, NB). posedirs: (207, V * 3).
        J_regressor: (24, V). parents: (24,) long. lbs_weights: (V, 24).

    Returns:
        vertices (B, V, 3) and joints (B, 24, 3), model units.
    """
    B = betas.shape[0]
    v_shaped = v_template + blend_shapes(betas, shapedirs)  # (B, V, 3)
    joints = torch.einsum("jv,bvk->bjk", J_regressor, v_shaped)  # (B, 24, 3)
    rot = batch_rodrigues(pose.reshape(-1, 3)).reshape(B, -1, 3, 3)  # (B, 24, 3, 3)
    eye = torch.eye(3, dtype=pose.dtype, device=pose.device)
    pose_feature = (rot[:, 1:] - eye).reshape(B, -1)  # (B, 207)
    v_posed = v_shaped + (pose_feature @ posedirs).reshape(B, -1, 3)
    posed_joints, T = batch_rigid_transform(rot, joints, parents)
    M = torch.einsum("vj,bjik->bvik", lbs_weights, T)  # (B, V, 4, 4)
    verts = torch.einsum("bvik,bvk->bvi", M[..., :3, :3], v_posed) + M[..., :3, 3]
    return verts, posed_joints


# --------------------------------------------------------------------------------------------- module
class SMPLTemplate(nn.Module):
    """SMPL posed by ``params = [transl (3), axis-angle pose (72), betas (num_betas)]``.

    Args:
        model: path of the user's model file (.npz / .pkl) or loaded ``SMPLModelData``.
        num_betas: shape coefficients used (<= the model's).
        scale: model units -> world units; 1000 maps SMPL metres to mm (translations too).
        uv_obj: optional OBJ with the SMPL UV layout (same faces, per-corner ``vt``); without it a
            new xatlas atlas is made (``deliffas.geometry.atlas``).
        atlas_res: xatlas packing resolution when no ``uv_obj`` is given.
        dtype: buffer dtype.
    """

    def __init__(self, model: str | os.PathLike | SMPLModelData, num_betas: int = 10, scale: float = 1000.0,
                 uv_obj: str | os.PathLike | None = None, atlas_res: int = 1024, dtype: torch.dtype = torch.float32):
        super().__init__()
        data = model if isinstance(model, SMPLModelData) else load_smpl_model(model)
        if not 0 <= num_betas <= data.num_betas:
            raise ValueError(f"num_betas: expected 0..{data.num_betas} (the model's), got {num_betas}")
        self.num_betas = int(num_betas)
        self.scale = float(scale)
        V = data.num_verts
        self.register_buffer("v_template", torch.tensor(data.v_template * scale, dtype=dtype))
        self.register_buffer("shapedirs", torch.tensor(data.shapedirs[:, :, :num_betas] * scale, dtype=dtype))
        posedirs = (data.posedirs * scale).reshape(V * 3, NUM_POSE_BASIS).T  # (207, V * 3)
        self.register_buffer("posedirs", torch.tensor(np.ascontiguousarray(posedirs), dtype=dtype))
        self.register_buffer("J_regressor", torch.tensor(data.J_regressor, dtype=dtype))
        self.register_buffer("lbs_weights", torch.tensor(data.weights, dtype=dtype))
        self.register_buffer("parents", torch.as_tensor(data.parents, dtype=torch.long))
        self.register_buffer("faces", torch.as_tensor(data.faces, dtype=torch.long))
        uvs, face_uvs = self._uvs(data, uv_obj, atlas_res)
        self.register_buffer("uvs", torch.tensor(uvs, dtype=dtype))
        self.register_buffer("face_uvs", torch.as_tensor(face_uvs, dtype=torch.long))

    def _uvs(self, data: SMPLModelData, uv_obj, atlas_res: int) -> tuple[np.ndarray, np.ndarray]:
        from deliffas.geometry.atlas import UVAtlas

        if uv_obj is not None:
            from deliffas.io.obj import read_obj

            obj = read_obj(uv_obj)
            if not obj.has_uvs or obj.num_faces != len(data.faces):
                raise SMPLModelError(f"{uv_obj}: expected {len(data.faces)} faces with per-corner uvs, "
                                     f"got {obj.num_faces} faces (uvs {'present' if obj.has_uvs else 'absent'})")
            if not np.array_equal(obj.faces, data.faces):
                raise SMPLModelError(f"{uv_obj}: its face list differs from the model's 'f'")
            return np.array(obj.uvs), np.array(obj.face_uvs)
        log.info("SMPLTemplate: no uv_obj given, computing an xatlas atlas for %d faces", len(data.faces))
        atlas = UVAtlas.from_mesh(data.v_template, data.faces, resolution=atlas_res)
        return np.array(atlas.uvs), np.array(atlas.face_uvs)

    @property
    def num_verts(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_dofs(self) -> int:
        """3 (translation) + 72 (pose) + num_betas."""
        return 3 + 3 * NUM_JOINTS + self.num_betas

    def rest_params(self, batch: int = 1) -> torch.Tensor:
        """(B, num_dofs) zeros: the T-pose with mean shape at the origin."""
        return torch.zeros(batch, self.num_dofs, dtype=self.v_template.dtype, device=self.v_template.device)

    def pose_with_joints(self, params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Vertices (B, V, 3) and joints (B, 24, 3), world units (mm with the default scale)."""
        check_shape("params", params, "B D", {"D": self.num_dofs})
        check_finite("params", params)
        params = params.to(self.v_template)
        transl = params[:, :3] * self.scale
        pose = params[:, 3:3 + 3 * NUM_JOINTS]
        betas = params[:, 3 + 3 * NUM_JOINTS:]
        verts, joints = smpl_lbs(betas, pose, self.v_template, self.shapedirs, self.posedirs, self.J_regressor,
                                 self.parents, self.lbs_weights)
        return verts + transl[:, None], joints + transl[:, None]

    def pose(self, params: torch.Tensor) -> torch.Tensor:
        """(B, 3 + 72 + num_betas) [transl (model units), axis-angle pose, betas] -> (B, V, 3) vertices."""
        return self.pose_with_joints(params)[0]

    def forward(self, params: torch.Tensor) -> torch.Tensor:
        return self.pose(params)
