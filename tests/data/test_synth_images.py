"""What synth's (image, mask) pairs mean: straight colour and coverage, as a photograph and its mask."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from deliffas.cli import main
from deliffas.data.render_gt import ShadingConfig, render_views
from deliffas.data.synth import SynthConfig, synthesize_capture
from deliffas.data.synth_config import check_synth_images
from deliffas.engine.samples import composite_target
from deliffas.io.formats.dynacap.frames import ImageFolderSource

BACKGROUND = (0.2, 0.4, 0.6)


def _triangle_view(scene: dict, supersample: int):
    """The triangle scene, flat and evenly lit (no specular: one colour everywhere), over a coloured background."""
    shading = ShadingConfig(specular=0.0, background=BACKGROUND, supersample=supersample)
    return render_views(**scene, shading=shading)[0]


def test_supersampled_edges_keep_the_straight_colour(triangle_scene):
    """At partial coverage the RGB is the surface's colour, not colour x coverage (+ background)."""
    view = _triangle_view(triangle_scene, 3)
    inside, outside = view.alpha == 255, view.alpha == 0
    partial = ~inside & ~outside
    assert partial.sum() >= 10
    colour = view.rgb[inside].astype(int)
    assert np.ptp(colour, axis=0).max() <= 1  # one colour: the edge must show it too
    assert np.abs(view.rgb[partial].astype(int) - colour[0]).max() <= 1
    assert (view.rgb[outside] == np.round(np.array(BACKGROUND) * 255)).all()


def test_point_sampled_views_are_colour_and_background(triangle_scene):
    """One ray per pixel: binary alpha, the surface's colour where it is hit, the background elsewhere."""
    one, three = _triangle_view(triangle_scene, 1), _triangle_view(triangle_scene, 3)
    assert set(np.unique(one.alpha)) <= {0, 255}
    assert (one.rgb[one.alpha == 0] == np.round(np.array(BACKGROUND) * 255)).all()
    assert np.abs(one.rgb[one.alpha == 255].astype(int) - three.rgb[three.alpha == 255][0]).max() <= 1


def test_supersampled_capture_composites_to_the_pixel_average(tmp_path, tiny_character):
    """``composite_target`` of a --supersample 2 capture is the 2 x 2 mean of the composite of the same
    capture point-sampled at twice the size (the same sub-pixel rays: f, cx, cy scale with the size)."""
    base = dict(num_frames=1, num_test_frames=1, num_cameras=2, seed=1, character=str(tiny_character))
    synthesize_capture(tmp_path / "ss", SynthConfig(width=32, height=32, supersample=2, **base))
    synthesize_capture(tmp_path / "fine", SynthConfig(width=64, height=64, supersample=1, **base))
    assert json.loads((tmp_path / "ss" / "synth.json").read_text())["images"] == "straight"
    ss, fine = ImageFolderSource(tmp_path / "ss" / "training"), ImageFolderSource(tmp_path / "fine" / "training")
    errors = []  # per camera, the largest error at fractional-mask pixels
    for cam in range(2):
        rgb, mask = ss.read(0, cam)
        frgb, fmask = fine.read(0, cam)
        assert set(np.unique(fmask)) <= {0, 255}  # point-sampled: a binary mask
        target = composite_target(rgb[None] / 255.0, mask[None] / 255.0)[0].numpy()
        fine_target = composite_target(frgb[None] / 255.0, fmask[None] / 255.0)[0].numpy()
        mean = fine_target.reshape(32, 2, 32, 2, 3).mean(axis=(1, 3))
        partial = (mask > 0) & (mask < 255)
        assert partial.sum() >= 10
        errors.append(np.abs(target - mean)[partial].max())
        assert np.abs(target - mean).max() < 1.5 / 255  # everywhere: 8-bit rounding only
    assert max(errors) < 1.5 / 255, errors


def test_check_synth_images(tmp_path):
    check_synth_images(tmp_path)  # no synth.json: a real capture
    path = tmp_path / "synth.json"
    path.write_text(json.dumps({"config": {"supersample": 1}}))
    check_synth_images(tmp_path)  # point-sampled: the same bytes before and after
    path.write_text(json.dumps({"config": {"supersample": 3}, "images": "straight"}))
    check_synth_images(tmp_path)
    path.write_text(json.dumps({"config": {"supersample": 3}}))
    with pytest.raises(ValueError, match=r"synth\.json: key 'images' is None, expected 'straight'.*--supersample 3"):
        check_synth_images(tmp_path)


def test_convert_refuses_a_premultiplied_capture(subject, tmp_path, capsys):
    """A capture synthesised with --supersample > 1 before synth wrote straight colour: one error line."""
    root = tmp_path / "subject"
    shutil.copytree(subject, root)
    record = json.loads((root / "synth.json").read_text())
    record["config"]["supersample"] = 2
    del record["images"]
    (root / "synth.json").write_text(json.dumps(record))
    capsys.readouterr()
    rc = main(["convert", str(root), str(tmp_path / "shards")])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "re-render it: deliffas synth" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "shards").exists()
