"""The web export of an SMPL-template run: its motion is the shaped rest mesh, its joints, skin and pose blend
shapes and per frame the pose and translation, and posed as the player poses them (a NumPy copy of
``player/smpl.js`` here; the page itself in Chromium) they are the vertices ``deliffas pose`` gives; in Chromium
the page's surfaces are built from them as ``deliffas render`` builds its own, and its frames agree with
``deliffas render``'s. A motion whose betas change between frames exports its posed vertices instead."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from deliffas.engine.export_config import ExportConfig
from deliffas.engine.web import export_web

from web_page import needs_chromium, page_frame, person_psnr, reference_frames, served_page

FRAMES = 2
VERTS_MM = 1e-3
"""The page's posing against ``deliffas pose``'s (mm), beside the float16 pose blend shapes' bound."""


@pytest.fixture(scope="module")
def smpl_page(tmp_path_factory):
    """(subject, run, page folder, motion file): a synthetic capture of the procedural SMPL-layout body, a run of
    one iteration on it, and its web export (the capture's test motion, two frames)."""
    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.synth import SynthConfig, synthesize_capture
    from deliffas.engine.train import TrainConfig, train

    root = tmp_path_factory.mktemp("web_smpl")
    synthesize_capture(root / "subject", SynthConfig(num_frames=3, num_test_frames=FRAMES, num_cameras=4, width=48,
                                                     height=48, test_cameras=(3,), seed=1, body_model="procedural",
                                                     fps=3.0))
    convert(root / "subject", root / "shards", ConvertConfig(atlas_res=32, progress=False))
    train(TrainConfig(shards=str(root / "shards"), out=str(root / "run"), model="two_surface", preset="tiny",
                      iters=1, num_workers=0, checkpoint_every=1, preview_every=0, progress=False))
    page = export_web(ExportConfig(run=root / "run", out=root / "page", web=True))
    return root / "subject", root / "run", page, _motion(root / "subject")


@pytest.fixture(scope="module")
def shaped_page(smpl_page, tmp_path_factory):
    """(subject, run, page folder, motion file): the same run's export of a 6-frame motion of a non-mean shape."""
    from deliffas.geometry.smpl_motion import procedural_smpl_motion
    from deliffas.io.body_models.amass import write_smpl_motion

    subject, run, _, _ = smpl_page
    root = tmp_path_factory.mktemp("web_smpl_shaped")
    betas = np.random.default_rng(7).normal(0, 1.0, 10)
    write_smpl_motion(root / "shaped.npz", procedural_smpl_motion(6, seed=5, fps=10.0, betas=betas))
    page = export_web(ExportConfig(run=run, out=root / "page", web=True, motion=root / "shaped.npz"))
    return subject, run, page, root / "shaped.npz"


def _motion(subject):
    return next((subject / "testing").glob("*.npz"))


def _arrays(page):
    """(index, motion entry, name -> its array) of an export."""
    index = json.loads((page / "avatar.json").read_text())
    blob = (page / "avatar.bin").read_bytes()
    dtypes = {"float32": "<f4", "int32": "<i4", "uint8": "u1"}

    def array(entry):
        a = np.frombuffer(blob, dtypes[entry["dtype"]], count=int(np.prod(entry["shape"])), offset=entry["offset"])
        return a.reshape(entry["shape"])

    motion = index["scene"]["motion"]
    return index, motion, lambda name: array(motion[name])


def _rodrigues(r):
    """(N, 3) -> (N, 3, 3), as player/smpl.js (and batch_rodrigues)."""
    angle = np.linalg.norm(r + 1e-8, axis=1)[:, None, None]
    x, y, z = (r / angle[:, :, 0]).T
    zero = np.zeros_like(x)
    K = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], 1).reshape(-1, 3, 3)
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _pose_like_the_player(motion, m):
    """(N, V, 3) float64: the exported arrays posed by player/smpl.js's formula."""
    v_shaped, joints = m("v_shaped").astype(np.float64), m("joints").astype(np.float64)
    parents, rows = motion["parents"], np.asarray(motion["pose_rows"])
    posedirs = m("posedirs")
    if motion["posedirs_dtype"] == "float16":
        posedirs = posedirs.reshape(len(rows), -1).view("<f2")
    posedirs = posedirs.astype(np.float64)
    idx, w = m("skin_indices").astype(np.int64), m("skin_weights").astype(np.float64)
    out = []
    for pose, transl in zip(m("poses").astype(np.float64), m("transl").astype(np.float64)):
        rot = _rodrigues(pose.reshape(-1, 3))
        feature = (rot[1:] - np.eye(3)).reshape(-1)[rows]
        v_posed = v_shaped + (feature @ posedirs).reshape(-1, 3)
        glob = []
        for j, p in enumerate(parents):
            local = np.eye(4)
            local[:3, :3] = rot[j]
            local[:3, 3] = joints[j] - (joints[p] if p >= 0 else 0)
            glob.append(local if p < 0 else glob[p] @ local)
        T = np.stack(glob)
        T[:, :3, 3] -= np.einsum("jik,jk->ji", T[:, :3, :3], joints)
        M = np.einsum("vk,vkab->vab", w, T[idx])
        out.append(np.einsum("vik,vk->vi", M[:, :3, :3], v_posed) + M[:, :3, 3] + transl)
    return np.stack(out)


@pytest.mark.parametrize("which", ["smpl_page", "shaped_page"])
def test_an_smpl_run_exports_what_poses_deliffas_pose_vertices(which, request):
    from deliffas.data.posing import pose_frames
    from deliffas.engine.avatar import run_capture

    subject, run, page, motion_file = request.getfixturevalue(which)
    index, motion, m = _arrays(page)
    assert motion["kind"] == "smpl" and "verts" not in motion and "verts" not in index["arrays"]
    assert index["scene"]["motion_file"] == motion_file.name
    meta, _ = run_capture(run)
    expected, template = pose_frames(meta.template_spec(), motion_file)  # the `deliffas pose` path, float64
    n = motion["frames"]
    assert n == min(len(expected), 300) and n >= 2 and not np.allclose(expected[0], expected[1], atol=1e-2)
    V = index["scene"]["num_verts"]
    assert m("v_shaped").shape == (V, 3) and m("joints").shape == (24, 3) and m("poses").shape == (n, 72)
    assert motion["parents"] == template.parents.tolist()
    # the skin: only exact zeros dropped
    dense = np.zeros((V, 24))
    np.add.at(dense, (np.arange(V)[:, None], m("skin_indices")), m("skin_weights"))
    np.testing.assert_array_equal(dense, template.lbs_weights.numpy().astype(np.float32))
    # the pose blend shapes: only all-zero rows dropped; float16 only within its bound
    rows = motion["pose_rows"]
    assert np.all(template.posedirs.numpy()[np.setdiff1d(np.arange(207), rows)] == 0)
    assert motion["posedirs_dtype"] in ("float16", "float32") and motion["posedirs_error_bound_mm"] <= 0.1
    got = _pose_like_the_player(motion, m)
    np.testing.assert_allclose(got, expected[:n], rtol=0, atol=VERTS_MM + motion["posedirs_error_bound_mm"])
    # with the model's own pose blend shapes the rest of the export is within VERTS_MM
    exact = template.posedirs.numpy()[rows]
    got = _pose_like_the_player({**motion, "posedirs_dtype": "float64"}, lambda k: exact if k == "posedirs" else m(k))
    np.testing.assert_allclose(got, expected[:n], rtol=0, atol=VERTS_MM)


def test_the_shape_is_the_motions(smpl_page, shaped_page):
    """The shaped page's rest mesh is its betas' (not the mean shape of the capture's motion)."""
    mean = _arrays(smpl_page[2])[2]("v_shaped")
    shaped = _arrays(shaped_page[2])[2]("v_shaped")
    assert np.abs(shaped - mean).max() > 5.0  # mm


def test_betas_that_change_between_frames_export_the_posed_vertices(smpl_page, caplog):
    import torch

    from deliffas.data.pose_motions import read_pose_motion
    from deliffas.engine.avatar import run_capture
    from deliffas.engine.render import motion_geometry_builder
    from deliffas.engine.web.bundle import Bundle
    from deliffas.engine.web.scene_pack import _pack_motion

    subject, run, _, motion_file = smpl_page
    meta, _ = run_capture(run)
    template, _ = motion_geometry_builder(meta)
    dofs = read_pose_motion(motion_file, meta.template_spec(), template.num_dofs).dofs.copy()
    dofs[1, 75] += 0.5  # the second frame's first beta
    bundle = Bundle()
    with caplog.at_level(logging.INFO, logger="deliffas.engine.web.scene_pack"), torch.no_grad():
        entry = _pack_motion(template, dofs, bundle)
    assert entry["kind"] == "vertices" and "betas change" in caplog.text
    assert set(bundle.entries) == {"verts"}
    verts = np.frombuffer(bundle.tobytes(), "<f4").reshape(entry["verts"]["shape"])
    with torch.no_grad():
        expected = template.pose(torch.as_tensor(dofs)).numpy()
    np.testing.assert_allclose(verts, expected, rtol=0, atol=1e-3)


@needs_chromium
def test_the_page_builds_the_smpl_surfaces_as_deliffas_does(smpl_page, shaped_page, tmp_path):
    """The page's posed surfaces and normal maps against ``deliffas pose`` and ``deliffas render``'s geometry,
    frame by frame, and its frames against ``deliffas render``'s (PSNR on the person)."""
    import torch

    from deliffas.data.pose_motions import read_pose_motion
    from deliffas.data.posing import pose_frames
    from deliffas.engine.avatar import run_capture
    from deliffas.engine.render import motion_geometry_builder

    subject, run, page, motion_file = smpl_page
    meta, _ = run_capture(run)
    template, builder = motion_geometry_builder(meta)
    motion = read_pose_motion(motion_file, meta.template_spec(), template.num_dofs)
    geo = builder.build(template.pose(torch.as_tensor(motion.dofs)).numpy())
    side = meta.atlas_res
    tol = VERTS_MM + _arrays(page)[1]["posedirs_error_bound_mm"]
    with served_page(page, tmp_path) as p:
        for f in range(FRAMES):
            got = p.evaluate("f => window.deliffasPlayer.geometry(f)", f)
            assert np.abs(np.reshape(got["inner"], (-1, 3)) - geo.inner[f]).max() < tol  # mm
            assert np.abs(np.reshape(got["outer"], (-1, 3)) - geo.outer[f]).max() < 1e-2
            nm = geo.normal_maps_inner[f].numpy()
            assert np.abs(np.reshape(got["nmInner"], (3, side, side)) - nm).max() < 1e-4
        pages = [page_frame(p, f, 3) for f in range(FRAMES)]
    refs = reference_frames(run, motion_file, 3, FRAMES, tmp_path / "ref")
    assert min(person_psnr(a, b) for a, b in zip(pages, refs)) >= 35.0
    _, _, shaped, shaped_motion = shaped_page
    expected, _ = pose_frames(meta.template_spec(), shaped_motion)
    tol = VERTS_MM + _arrays(shaped)[1]["posedirs_error_bound_mm"]
    (tmp_path / "shaped").mkdir()
    with served_page(shaped, tmp_path / "shaped") as p:
        for f in (0, len(expected) - 1):
            got = p.evaluate("f => window.deliffasPlayer.geometry(f)", f)
            assert np.abs(np.reshape(got["inner"], (-1, 3)) - expected[f]).max() < tol  # mm
