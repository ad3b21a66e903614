"""SMPLTemplate on synthetic model files (nothing shipped or downloaded): loading, safety, maths."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from deliffas.geometry.templates import SMPLTemplate
from deliffas.io.body_models.smpl import SMPLModelError, load_smpl_model
from deliffas.geometry.templates import Template

PARENTS = np.array([-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21])


def _synthetic_arrays(seed: int = 0) -> dict:
    """A small SMPL-shaped model: an icosphere body, random small blend shapes, SMPL's kinematic tree."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    rng = np.random.default_rng(seed)
    V = len(m.vertices)
    J = rng.random((24, V)) ** 4
    J /= J.sum(1, keepdims=True)
    W = rng.random((V, 24)) ** 6
    W /= W.sum(1, keepdims=True)
    kintree = np.stack([np.where(PARENTS < 0, 4294967295, PARENTS), np.arange(24)]).astype(np.int64)
    return dict(v_template=np.asarray(m.vertices, np.float64), shapedirs=rng.normal(0, 0.01, (V, 3, 10)),
                posedirs=rng.normal(0, 0.002, (V, 3, 207)), J_regressor=J, weights=W, kintree_table=kintree,
                f=np.asarray(m.faces, np.uint32))


@pytest.fixture(scope="module")
def model_npz(tmp_path_factory):
    p = tmp_path_factory.mktemp("smpl") / "smpl_synthetic.npz"
    np.savez(p, **_synthetic_arrays())
    return p


def _rodrigues_np(r):
    a = np.linalg.norm(r)
    if a < 1e-12:
        return np.eye(3)
    k = r / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def _reference_smpl(d: dict, transl, pose, betas, scale=1000.0):
    """Loop reference: SMPL forward in float64 numpy, one joint and one vertex formula at a time."""
    v_shaped = d["v_template"] + d["shapedirs"][:, :, : len(betas)] @ betas
    joints = d["J_regressor"] @ v_shaped
    R = [_rodrigues_np(pose[3 * j:3 * j + 3]) for j in range(24)]
    feat = np.concatenate([(R[j] - np.eye(3)).ravel() for j in range(1, 24)])
    v_posed = v_shaped + d["posedirs"] @ feat
    G = []
    for j in range(24):
        L = np.eye(4)
        L[:3, :3] = R[j]
        L[:3, 3] = joints[j] - (joints[PARENTS[j]] if j else 0)
        G.append(L if j == 0 else G[PARENTS[j]] @ L)
    A = []
    for j in range(24):
        T = G[j].copy()
        T[:3, 3] -= G[j][:3, :3] @ joints[j]
        A.append(T)
    A = np.stack(A)
    M = np.einsum("vj,jab->vab", d["weights"], A)
    out = np.einsum("vab,vb->va", M[:, :3, :3], v_posed) + M[:, :3, 3]
    return (out + transl) * scale


def test_round_trip_against_reference(model_npz):
    d = _synthetic_arrays()
    t = SMPLTemplate(model_npz, dtype=torch.float64)
    assert isinstance(t, Template)
    assert t.num_dofs == 85 and t.num_verts == len(d["v_template"])
    rng = np.random.default_rng(3)
    params = np.zeros((3, 85))
    params[1, 3:75] = rng.normal(0, 0.4, 72)
    params[2] = np.concatenate([[0.1, -0.2, 0.3], rng.normal(0, 0.3, 72), rng.normal(0, 1.0, 10)])
    v = t.pose(torch.tensor(params)).numpy()
    for b in range(3):
        ref = _reference_smpl(d, params[b, :3], params[b, 3:75], params[b, 75:])
        np.testing.assert_allclose(v[b], ref, atol=1e-3)  # mm; batch_rodrigues adds 1e-8 to the angle
    np.testing.assert_allclose(v[0], d["v_template"] * 1000, atol=1e-3)
    metres = SMPLTemplate(model_npz, scale=1.0, dtype=torch.float64).pose(torch.tensor(params[2:]))
    np.testing.assert_allclose(metres[0].numpy() * 1000, v[2], atol=1e-6)
    assert t.faces.shape == (len(d["f"]), 3) and t.face_uvs.shape == t.faces.shape, "xatlas uvs without a uv OBJ"


def test_pkl_with_sparse_regressor_loads_like_npz(model_npz, tmp_path):
    d = _synthetic_arrays()
    d["J_regressor"] = sp.csc_matrix(d["J_regressor"])
    ref = load_smpl_model(model_npz)
    for protocol in (2, 5):
        p = tmp_path / f"model_p{protocol}.pkl"
        with open(p, "wb") as fh:
            pickle.dump(d, fh, protocol=protocol)
        m = load_smpl_model(p)
        np.testing.assert_allclose(m.J_regressor, ref.J_regressor)
        np.testing.assert_array_equal(m.parents, PARENTS)
        np.testing.assert_array_equal(m.faces, ref.faces)


class _Evil:
    def __reduce__(self):
        import os

        return (os.system, ("touch EVIL_MARKER",))


def test_pkl_with_disallowed_class_is_refused(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    p = tmp_path / "evil.pkl"
    d = _synthetic_arrays()
    d["weights"] = _Evil()
    with open(p, "wb") as fh:
        pickle.dump(d, fh, protocol=2)
    with pytest.raises(SMPLModelError, match=r"refusing to load '(posix|nt|os)\.system'"):
        load_smpl_model(p)
    assert not (tmp_path / "EVIL_MARKER").exists(), "nothing was executed"


def test_chumpy_pickle_gets_a_conversion_hint(tmp_path):
    p = tmp_path / "chumpy.pkl"
    p.write_bytes(b"\x80\x02}q\x00X\n\x00\x00\x00v_templateq\x01cchumpy.ch\nCh\nq\x02)\x81q\x03s.")
    with pytest.raises(SMPLModelError, match=r"chumpy.*\.npz"):
        load_smpl_model(p)


def test_missing_file_names_path_and_license(tmp_path):
    missing = tmp_path / "models" / "SMPL_NEUTRAL.pkl"
    with pytest.raises(FileNotFoundError) as err:
        SMPLTemplate(missing)
    msg = str(err.value)
    assert str(missing) in msg and "not shipped" in msg and "smpl.is.tue.mpg.de" in msg


@pytest.mark.parametrize("key, bad", [("posedirs", np.zeros((42, 3, 200))), ("J_regressor", np.zeros((23, 42))),
                                      ("kintree_table", np.array([[0] * 24, list(range(24))]))])
def test_wrong_layout_is_refused(tmp_path, key, bad):
    d = _synthetic_arrays()
    d[key] = bad
    p = tmp_path / "bad.npz"
    np.savez(p, **d)
    with pytest.raises(SMPLModelError, match=key):
        load_smpl_model(p)


def test_uv_obj_and_num_betas(model_npz, tmp_path):
    from deliffas.io.obj import ObjData, write_obj

    d = _synthetic_arrays()
    F = len(d["f"])
    uvs = np.random.default_rng(0).random((3 * F, 2))
    obj = tmp_path / "smpl_uv.obj"
    write_obj(obj, ObjData(d["v_template"], d["f"].astype(np.int64), uvs, np.arange(3 * F).reshape(F, 3)))
    t = SMPLTemplate(model_npz, num_betas=4, uv_obj=obj)
    assert t.num_dofs == 3 + 72 + 4
    np.testing.assert_allclose(t.uvs.numpy(), uvs, atol=1e-6)
    out = t.pose(torch.zeros(2, t.num_dofs))
    assert out.dtype == torch.float32 and out.shape == (2, t.num_verts, 3)
    with pytest.raises(ValueError, match="params"):
        t.pose(torch.zeros(2, 85))
    with pytest.raises(ValueError, match="num_betas"):
        SMPLTemplate(model_npz, num_betas=11, uv_obj=obj)
