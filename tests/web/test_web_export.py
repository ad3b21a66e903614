"""deliffas export --web: the folder it writes, the variants it refuses, and what it never overwrites."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from deliffas.cli import main
from deliffas.engine.export_config import ExportConfig
from deliffas.engine.web import PLAYER_FILES, WEB_FORMAT, export_web, supported_variants
from deliffas.models.model_table import DEFAULT_MODEL, model_row


def _arrays(folder: Path) -> tuple[dict, bytes]:
    return json.loads((folder / "avatar.json").read_text()), (folder / "avatar.bin").read_bytes()


def test_the_folder_holds_the_page_the_player_and_every_array(web_runs, tmp_path):
    run = web_runs(DEFAULT_MODEL, "tiny")
    out = export_web(ExportConfig(run=run, out=tmp_path / "page", web=True))
    names = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    assert names == {*PLAYER_FILES, "avatar.json", "avatar.bin"}
    index, blob = _arrays(out)
    assert {k: index[k] for k in WEB_FORMAT} == WEB_FORMAT and index["bin_bytes"] == len(blob)
    model = index["model"]
    assert model["variant"] == model_row(DEFAULT_MODEL).variant and model["texture_inner"]["channels"] == 8
    assert model["unet_outer"] is not None and model["spec"]["reflect_viewdir"]
    for name, entry in index["arrays"].items():
        size = int(np.prod(entry["shape"])) * 4 if entry["dtype"] != "uint8" else int(np.prod(entry["shape"]))
        assert entry["offset"] % 4 == 0 and entry["offset"] + size <= len(blob), name
    scene = index["scene"]
    assert scene["motion"]["kind"] == "skinned" and scene["motion"]["frames"] == 3  # the capture's test motion
    assert len(scene["cameras"]) == 4 and scene["test_cameras"] == [3]
    assert 'type="module" src="player/main.js"' in (out / "index.html").read_text()
    assert not list(tmp_path.glob(".page*"))  # no temporary folder left beside it


def test_an_avatar_file_exports_as_its_run_does(web_runs, tmp_path):
    from deliffas.engine.avatar import export_avatar

    run = web_runs("two_surface", "tiny")
    avatar = export_avatar(ExportConfig(run=run, out=tmp_path / "a.avatar"))
    pages = [export_web(ExportConfig(run=src, out=tmp_path / name, web=True))
             for src, name in ((run, "r"), (avatar, "a"))]
    assert (pages[0] / "avatar.bin").read_bytes() == (pages[1] / "avatar.bin").read_bytes()


def test_a_failed_write_leaves_no_folder(web_runs, tmp_path, monkeypatch):
    import deliffas.engine.web.export as export

    def broken(tmp, index, bundle):
        (tmp / "avatar.json").write_text("{")
        raise OSError("disk full")

    monkeypatch.setattr(export, "_write_folder", broken)
    with pytest.raises(OSError, match="disk full"):
        export_web(ExportConfig(run=web_runs("two_surface", "tiny"), out=tmp_path / "page", web=True))
    assert not list(tmp_path.iterdir())


def test_an_unsupported_variant_is_refused_with_the_supported_ones(web_runs, tmp_path, capsys):
    run = web_runs("single_surface_two_unet", "tiny")
    assert main(["export", str(run), str(tmp_path / "page"), "--web"]) == 2
    err = capsys.readouterr().err
    assert "single_surface_two_unet" in err and "Traceback" not in err
    assert all(v in err for v in supported_variants()) and "two_surface_reflect" in supported_variants()
    assert not (tmp_path / "page").exists() and not list(tmp_path.iterdir())


def test_an_existing_folder_is_kept_without_overwrite(web_runs, tmp_path, capsys):
    run, out = web_runs("two_surface", "tiny"), tmp_path / "page"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    assert main(["export", str(run), str(out), "--web"]) == 2
    assert "not a web export" in capsys.readouterr().err and (out / "mine.txt").read_text() == "keep"
    assert main(["export", str(run), str(out), "--web", "--overwrite"]) == 2  # not a web export: never replaced
    assert "not a web export" in capsys.readouterr().err and (out / "mine.txt").read_text() == "keep"
    (out / "mine.txt").unlink()
    assert main(["export", str(run), str(out), "--web", "--frames", "3"]) == 0  # an empty folder is taken
    assert main(["export", str(run), str(out), "--web", "--frames", "2"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["export", str(run), str(out), "--web", "--overwrite", "--frames", "2"]) == 0  # ours is replaced
    assert _arrays(out)[0]["scene"]["motion"]["frames"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["page"]


def test_an_output_that_is_neither_a_folder_nor_an_avatar_file_is_refused_at_parse_time(capsys):
    with pytest.raises(SystemExit) as info:
        main(["export", "r", "page.zip", "--web"])
    assert info.value.code == 2 and "ending in .avatar" in capsys.readouterr().err


@pytest.mark.parametrize("argv, match", [(["r", "x.avatar", "--web"], "--web writes a folder"),
                                         (["r", "x.avatar", "--frames", "3"], "only with --web")])
def test_options_that_do_not_fit_the_output_are_refused(argv, match, capsys):
    assert main(["export", *argv]) == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err


def test_u_nets_below_the_atlas_side_are_accepted_and_exported():
    from deliffas.engine.web.bundle import Bundle
    from deliffas.engine.web.model_pack import check_web_supported, pack_model
    from deliffas.models import get_config
    from deliffas.models.deliffas import DeliffasModel

    config = dataclasses.replace(get_config("two_surface_reflect_texture", "tiny"), unet_downsample=2)
    check_web_supported(config)  # no ValueError
    model = pack_model(DeliffasModel(config).eval(), Bundle())
    assert model["unet_downsample"] == 2 and model["atlas_res"] == config.atlas_res
    assert model["unet_inner"]["levels"] == int(np.log2(config.atlas_res // 2))  # down to 1 x 1 from S / 2
    with pytest.raises(ValueError, match="texture_scale 2"):  # finer atlases stay refused
        check_web_supported(dataclasses.replace(config, texture_scale=2))
