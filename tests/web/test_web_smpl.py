"""The web export of an SMPL-template run: its motion is the posed vertices of every frame (the player skins
nothing), and they are the vertices ``deliffas pose`` gives; in Chromium the page's surfaces are built from them as
``deliffas render`` builds its own."""

from __future__ import annotations

import json

import numpy as np
import pytest

from deliffas.engine.export_config import ExportConfig
from deliffas.engine.web import export_web

from web_page import needs_chromium, served_page

FRAMES = 2


@pytest.fixture(scope="module")
def smpl_page(tmp_path_factory):
    """(subject, run, page folder): a synthetic capture of the procedural SMPL-layout body, a run of one
    iteration on it, and its web export (the capture's test motion, two frames)."""
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
    return root / "subject", root / "run", page


def _motion(subject):
    return next((subject / "testing").glob("*.npz"))


def test_an_smpl_run_exports_the_posed_vertices_of_every_frame(smpl_page):
    from deliffas.data.posing import pose_frames
    from deliffas.engine.avatar import run_capture

    subject, run, page = smpl_page
    index = json.loads((page / "avatar.json").read_text())
    blob = (page / "avatar.bin").read_bytes()
    motion = index["scene"]["motion"]
    assert motion["kind"] == "vertices" and motion["frames"] == FRAMES and "bones" not in index["arrays"]
    assert index["scene"]["motion_file"] == _motion(subject).name
    entry = motion["verts"]
    assert entry["dtype"] == "float32"
    verts = np.frombuffer(blob, "<f4", count=int(np.prod(entry["shape"])), offset=entry["offset"])
    verts = verts.reshape(entry["shape"])
    meta, _ = run_capture(run)
    expected, _ = pose_frames(meta.template_spec(), _motion(subject))  # the `deliffas pose` path, float64
    assert meta.template_spec().kind == "smpl" and verts.shape == (FRAMES, index["scene"]["num_verts"], 3)
    assert not np.allclose(expected[0], expected[1], atol=1e-2)  # two different poses
    np.testing.assert_allclose(verts, expected[:FRAMES], rtol=0, atol=1e-3)  # mm; float32 of values ~1e3 mm


@needs_chromium
def test_the_page_builds_the_smpl_surfaces_as_deliffas_does(smpl_page, tmp_path):
    """The page's posed surfaces and normal maps against ``deliffas render``'s geometry, frame by frame."""
    import torch

    from deliffas.data.pose_motions import read_pose_motion
    from deliffas.engine.avatar import run_capture
    from deliffas.engine.render import motion_geometry_builder

    subject, run, page = smpl_page
    meta, _ = run_capture(run)
    template, builder = motion_geometry_builder(meta)
    motion = read_pose_motion(_motion(subject), meta.template_spec(), template.num_dofs)
    geo = builder.build(template.pose(torch.as_tensor(motion.dofs)).numpy())
    side = meta.atlas_res
    with served_page(page, tmp_path) as p:
        for f in range(FRAMES):
            got = p.evaluate("f => window.deliffasPlayer.geometry(f)", f)
            assert np.abs(np.reshape(got["inner"], (-1, 3)) - geo.inner[f]).max() < 1e-2  # mm
            assert np.abs(np.reshape(got["outer"], (-1, 3)) - geo.outer[f]).max() < 1e-2
            nm = geo.normal_maps_inner[f].numpy()
            assert np.abs(np.reshape(got["nmInner"], (3, side, side)) - nm).max() < 1e-4
