"""Geometry bad cases: each gives a clear error or a documented, tested fallback (docs/reliability.md).

| case | behaviour |
|---|---|
| non-watertight template | ``shell_report`` and ``convert`` log a warning naming the boundary vertices (rays through a hole see the inside of the far side: back faces) |
| zero-area (degenerate) faces, isolated vertices | vertex normal (0, 0, 0) with ``valid`` False, offset 0 (vertex stays), finite normal maps |
| zero-area UV faces | cover no texel, listed in ``TexelTable.degenerate_faces``, warning with their ids |
| NaN / inf poses, vertices, cameras; singular K; face index out of range | ``ValueError`` naming the array (readers: ``DynaCapFormatError``) |
| camera looking away from the subject | zero shaded rays, black render, ``shell_report`` note, synthetic view with zero alpha, ``train_step`` skipped (no NaN, no parameter change) |
| empty foreground (mask all 0) | L1 on the shell's rays against black, finite; perceptual patches fall back to the whole image |
"""

from __future__ import annotations

import dataclasses
import logging
import shutil

import numpy as np
import pytest
import torch
from reliability_support import CONVERT_KW, COUNTS

from deliffas.io.cameras import Camera
from deliffas.geometry.atlas import UVAtlas, uv_texel_table
from deliffas.geometry.frame_geometry import FrameGeometryBuilder
from deliffas.geometry.mesh_ops import vertex_normals
from deliffas.geometry.raycast import UVRaycaster, build_scene, uv_inner_or_exit
from deliffas.geometry.shell import offset_shell, self_intersecting_faces, shell_report

pytestmark = pytest.mark.timeout(300)


def _octahedron(scale: float = 300.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A closed, outward-oriented octahedron with per-corner uvs (one chart per face)."""
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float) * scale
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    uvs, face_uvs = [], []
    for i in range(len(f)):
        x0, y0 = (i % 4) / 4 + 0.02, (i // 4) / 2 + 0.02
        uvs += [[x0, y0], [x0 + 0.2, y0], [x0, y0 + 0.4]]
        face_uvs.append([3 * i, 3 * i + 1, 3 * i + 2])
    return v, f, np.array(uvs), np.array(face_uvs)


def _camera(eye_z: float = 2000.0, width: int = 48, height: int = 48, away: bool = False) -> Camera:
    """Camera on the +z axis looking at the origin (or away from it)."""
    K = np.array([[60.0, 0, width / 2], [0, 60.0, height / 2], [0, 0, 1]])
    R = np.diag([-1.0, 1.0, -1.0]) if not away else np.eye(3)  # camera +z = world -z (towards the origin)
    E = np.eye(4)
    E[:3, :3] = R
    E[:3, 3] = -R @ np.array([0, 0, eye_z])
    return Camera("away" if away else "front", K, E, width, height)


def _away(cam: Camera) -> Camera:
    """The same camera turned by 180 degrees about its y axis (the subject is behind it)."""
    flip = np.diag([-1.0, 1.0, -1.0, 1.0])
    return dataclasses.replace(cam, world_to_cam=flip @ cam.world_to_cam)


# ------------------------------------------------------------------------------------- non-watertight
def test_non_watertight_mesh_is_reported_with_where(caplog):
    v, f, uvs, fu = _octahedron()
    holed = f[1:]  # drop face 0 = (0, 2, 4)
    outer = offset_shell(v, holed, 30.0)
    with caplog.at_level(logging.WARNING):
        rep = shell_report(v, holed, outer)
    assert not rep.watertight and rep.num_boundary_edges == 3 and rep.boundary_vertex_ids == [0, 2, 4]
    assert "not watertight" in caplog.text and "[0, 2, 4]" in caplog.text
    # What rays through the hole see (why it is a warning): the inside of the far side, i.e. back faces,
    # with finite uvs; nothing fails, the images are wrong there.
    rc = UVRaycaster(v.astype(np.float32), holed, outer.astype(np.float32), UVAtlas(uvs, fu[1:]))
    origin = v[[0, 2, 4]].mean(0) * 10
    direction = -origin / np.linalg.norm(origin)
    hits = rc.cast_rays(origin[None], direction[None])
    uv, from_outer = uv_inner_or_exit(hits)
    assert hits.outer_hit[0] and hits.inner_hit[0] and not from_outer[0] and np.isfinite(uv).all()
    a, b, c = v[holed[hits.inner_face[0]]]
    assert np.dot(np.cross(b - a, c - a), direction) > 0  # a back face
    COUNTS["geometry: bad cases checked"] += 1


def test_convert_warns_on_a_non_watertight_template(rel_subject, rel_character, tmp_path, caplog):
    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.io.formats.dynacap.character import read_obj, write_obj
    from deliffas.data.shards import verify_shards

    char_dir = tmp_path / "character"
    shutil.copytree(rel_character.parent, char_dir)
    obj_path = next(p for p in char_dir.glob("*.obj") if not p.name.endswith("_graph.obj"))
    obj = read_obj(obj_path)
    fn = None if obj.face_normals_idx is None else obj.face_normals_idx[1:]
    write_obj(obj_path, dataclasses.replace(obj, faces=obj.faces[1:], face_uvs=obj.face_uvs[1:], face_normals_idx=fn))
    with caplog.at_level(logging.WARNING, logger="deliffas.data.convert"):
        convert(rel_subject, tmp_path / "out", ConvertConfig(**CONVERT_KW, frames="0:2", sequences=("training",),
                                                            template=str(char_dir / rel_character.name),
                                                            progress=False))
    assert "not watertight" in caplog.text and str(sorted(int(i) for i in obj.faces[0])) in caplog.text
    assert verify_shards(tmp_path / "out").problems == ()
    COUNTS["geometry: bad cases checked"] += 1


# ------------------------------------------------------------------------------------- degenerate faces
def test_degenerate_faces_and_isolated_vertices_get_zero_normals_and_stay():
    v, f, uvs, fu = _octahedron()
    v = np.vstack([v, v[0], v[0], [[5.0, 5.0, 5.0]]])  # 6, 7: coincident with 0; 8: isolated
    f_bad = np.vstack([f, [[0, 6, 7], [6, 7, 0]]])  # zero-area faces
    normals, valid = vertex_normals(v, f_bad, return_valid=True)
    assert np.isfinite(normals).all()
    assert valid[:6].all() and not valid[6:].any() and np.allclose(normals[6:], 0)
    outer = offset_shell(v, f_bad, 30.0)
    assert np.allclose(outer[6:], v[6:]) and np.isfinite(outer).all()  # no normal: the vertex stays
    assert len(self_intersecting_faces(v, f_bad)) == 0  # zero-area faces are not reported as crossings
    fu_bad = np.vstack([fu, [[0, 1, 2], [0, 1, 2]]])
    table = uv_texel_table(UVAtlas(uvs, fu_bad), 16)
    geo = FrameGeometryBuilder(f_bad, np.full(len(v), 30.0), table).build(v[None])
    assert torch.isfinite(geo.normal_maps_inner).all() and torch.isfinite(geo.normal_maps_outer).all()
    rc = UVRaycaster(v.astype(np.float32), f_bad, outer.astype(np.float32), UVAtlas(uvs, fu_bad))
    hits = rc.cast(_camera())
    assert hits.outer_hit.any() and np.isfinite(hits.uv_outer[hits.outer_hit]).all()
    COUNTS["geometry: bad cases checked"] += 1


def test_zero_area_uv_faces_cover_nothing_and_are_listed(caplog):
    v, f, uvs, fu = _octahedron()
    fu = fu.copy()
    fu[3] = [9, 9, 9]  # a point
    fu[5] = [15, 16, 15]  # a segment
    with caplog.at_level(logging.WARNING):
        table = uv_texel_table(UVAtlas(uvs, fu), 32)
    assert table.degenerate_faces.tolist() == [3, 5]
    assert "2 zero-area UV faces" in caplog.text and "[3, 5]" in caplog.text
    assert not np.isin(table.face[table.covered], [3, 5]).any()
    assert np.isfinite(table.bary).all() and table.valid.any()
    COUNTS["geometry: bad cases checked"] += 1


# ------------------------------------------------------------------------------------- non-finite input
def test_non_finite_inputs_raise_naming_the_array(rel_character, tmp_path):
    from deliffas.io.formats.dynacap.character import DynaCapFormatError, read_character, read_motion, write_motion
    from deliffas.io.motion import Motion
    from deliffas.geometry.templates import DDCTemplate

    character = read_character(rel_character)
    template = DDCTemplate(character)
    dofs = torch.zeros(2, template.num_dofs)
    assert torch.isfinite(template.pose(dofs)).all()
    cases = 0
    for bad in (float("nan"), float("inf")):
        d = dofs.clone()
        d[1, 3] = bad
        with pytest.raises(ValueError, match=r"dofs: 1 non-finite"):
            template.pose(d)
        cases += 1
    m = Motion(np.arange(2), np.zeros((2, template.num_dofs)))
    m.dofs[1, 2] = np.nan
    write_motion(tmp_path / "nan.motion", m)
    with pytest.raises(DynaCapFormatError, match=r"nan\.motion:3: expected finite"):
        read_motion(tmp_path / "nan.motion", template.num_dofs)
    v, f, uvs, fu = _octahedron()
    vn = v.copy()
    vn[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"verts: 1 non-finite"):
        build_scene(vn, f)
    with pytest.raises(ValueError, match=r"faces: indices must be in \[0, 6\)"):
        build_scene(v, np.vstack([f, [[0, 1, 6]]]))
    table = uv_texel_table(UVAtlas(uvs, fu), 8)
    with pytest.raises(ValueError, match=r"inner: 1 non-finite"):
        FrameGeometryBuilder(f, np.full(6, 30.0), table).build(vn[None])
    cam = _camera()
    for field, bad in (("K", np.nan), ("world_to_cam", np.inf)):
        arr = getattr(cam, field).copy()
        arr[0, 0] = bad
        with pytest.raises(ValueError, match=rf"camera front {field}: 1 non-finite"):
            dataclasses.replace(cam, **{field: arr})
    K0 = cam.K.copy()
    K0[1, 1] = 0.0
    with pytest.raises(ValueError, match="expected positive focal lengths"):
        dataclasses.replace(cam, K=K0)
    from deliffas.io.formats.dynacap.calibration import read_calibration, write_calibration

    write_calibration(tmp_path / "c.calibration", [cam])
    text = (tmp_path / "c.calibration").read_text().splitlines()
    row = next(i for i, line in enumerate(text) if line.split()[:1] == ["intrinsic"])
    text[row] = "  intrinsic " + " ".join(["0.0"] + text[row].split()[2:])
    (tmp_path / "c.calibration").write_text("\n".join(text) + "\n")
    with pytest.raises(DynaCapFormatError, match=r"c\.calibration:\d+: camera 'front'.*positive focal"):
        read_calibration(tmp_path / "c.calibration")
    cases += 8
    COUNTS["geometry: bad cases checked"] += cases


# ------------------------------------------------------------------------------------- looking away
def test_camera_looking_away_sees_nothing(rel_character):
    from deliffas.io.formats.dynacap.character import read_character
    from deliffas.data.render_gt import render_views
    from deliffas.engine.rays import camera_rays

    v, f, uvs, fu = _octahedron()
    outer = offset_shell(v, f, 30.0)
    away = _camera(away=True)
    rc = UVRaycaster(v.astype(np.float32), f, outer.astype(np.float32), UVAtlas(uvs, fu))
    assert camera_rays(rc, _camera()).num_rays > 0
    assert camera_rays(rc, away).num_rays == 0
    rep = shell_report(v, f, outer, cameras=[away])
    assert rep.num_rays_inner == 0 and rep.outer_first_fraction is None
    assert "no camera ray hits the inner surface" in rep.notes
    character = read_character(rel_character)
    texture = np.full((8, 8, 3), 0.5, np.float32)
    mesh = character.mesh
    view_front, view_away = render_views(np.asarray(mesh.verts), mesh.faces, mesh.uvs, mesh.face_uvs, texture,
                                         [_camera(3000.0), _camera(3000.0, away=True)])
    assert view_front.alpha.any()
    assert not view_away.alpha.any() and not view_away.rgb.any()  # a synthetic empty-foreground view
    COUNTS["geometry: bad cases checked"] += 2


@pytest.fixture(scope="module")
def sample_and_info(rel_reference):
    from deliffas.engine.data_bridge import evaluation_samples

    samples, info = evaluation_samples(str(rel_reference), "all", max_frames=1, with_rays=True, protocol="all")
    return next(iter(samples)), info


def _tiny_model(info):
    from deliffas.engine.train import TrainConfig, resolve_model_config
    from deliffas.models import DeliffasModel

    cfg = resolve_model_config(TrainConfig(shards="-", out="-", preset="tiny"), info["atlas_res"],
                               info["temporal_window"])
    torch.manual_seed(0)
    model = DeliffasModel(cfg)
    return model, torch.optim.Adam(model.parameters(), lr=1e-3)


def test_train_step_skips_a_sample_whose_cameras_all_look_away(sample_and_info):
    from deliffas.engine.shading import render_frame
    from deliffas.engine.rays import frame_rays
    from deliffas.engine.timing import StageTimer
    from deliffas.engine.train import train_step

    sample, info = sample_and_info
    assert all(r.num_rays > 0 for r in sample.rays)
    cams = [_away(c) for c in sample.cameras]
    rays = frame_rays(sample.inner_verts, sample.outer_verts, info["faces"], info["atlas"], cams)
    assert [r.num_rays for r in rays] == [0] * len(cams)
    empty = dataclasses.replace(sample, cameras=cams, rays=rays)
    model, opt = _tiny_model(info)
    cpu = torch.device("cpu")
    first = train_step(model, sample, opt, cpu)  # Adam has momentum now: a zero-gradient step would still move
    assert np.isfinite(first["loss"]) and first["skipped"] == 0
    before = {k: v.clone() for k, v in model.state_dict().items()}
    out = train_step(model, empty, opt, cpu)
    assert out["skipped"] == 1 and out["loss"] == 0 and np.isnan(out["psnr_rays"])
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items()), "a skipped step changed the model"
    mixed = dataclasses.replace(sample, cameras=[cams[0]] + sample.cameras[1:], rays=[rays[0]] + sample.rays[1:])
    out = train_step(model, mixed, opt, cpu)
    assert out["skipped"] == 0 and np.isfinite(out["loss"]) and np.isfinite(out["psnr_rays"])
    assert all(torch.isfinite(p).all() for p in model.parameters())
    with torch.no_grad():
        model.eval()
        rc = UVRaycaster(sample.inner_verts, info["faces"], sample.outer_verts, info["atlas"])
        images = render_frame(model, empty, rc, cpu, StageTimer(cpu), chunk_size=64)
    assert images.shape[0] == len(cams) and not images.any()  # black, not NaN
    COUNTS["geometry: bad cases checked"] += 3


def test_empty_foreground_trains_on_black(sample_and_info):
    from deliffas.engine.train import train_step
    from deliffas.models.losses import foreground_patches

    sample, info = sample_and_info
    blank = dataclasses.replace(sample, masks=np.zeros_like(sample.masks))
    model, opt = _tiny_model(info)
    out = train_step(model, blank, opt, torch.device("cpu"))
    assert out["skipped"] == 0 and np.isfinite(out["loss"]) and out["loss"] > 0
    H, W = sample.masks.shape[1:]
    tl = foreground_patches(torch.zeros(2, H, W), (H, W), 2, 16, 8, torch.Generator().manual_seed(0))
    assert tl.min() >= 0 and int(tl[..., 0].max()) <= H - 16 and int(tl[..., 1].max()) <= W - 16
    COUNTS["geometry: bad cases checked"] += 2
