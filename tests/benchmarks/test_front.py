"""benchmarks.front: the speed/accuracy front's table, JSON and chart from trained runs."""

import json

import pytest

from benchmarks import front
from deliffas.engine.train import TrainConfig, train


@pytest.fixture(scope="module")
def runs(tiny_shards, tmp_path_factory):
    root = tmp_path_factory.mktemp("front")
    made = []
    for seed in (0, 1):
        run = root / f"s{seed}"
        train(TrainConfig(shards=str(tiny_shards), out=str(run), model="two_surface", preset="tiny", iters=2,
                          cameras_per_frame=2, protocol="all", validation_cameras=1, seed=seed, num_workers=0,
                          checkpoint_every=2, preview_every=0, log_every=1, progress=False))
        made.append(str(run))
    return made


def test_front_scores_every_run_and_marks_the_front(runs, tmp_path, monkeypatch):
    monkeypatch.setattr(front, "SIZE", (40, 32))
    monkeypatch.setattr(front, "FRAMES", 2)
    rows = front.main([f"a={runs[0]},{runs[1]}", f"b={runs[1]}", "--out", str(tmp_path), "--max-frames", "1",
                       "--rounds", "1"])
    by = {r["name"]: r for r in rows}
    assert len(by["a"]["validation_masked_runs"]) == 2 and len(by["b"]["novel_view_fg_runs"]) == 1
    assert all(r["fps"] > 0 for r in rows) and any(r["front"] for r in rows)
    best = max(rows, key=lambda r: r["validation_masked"])
    assert best["front"]  # the most accurate is never beaten in both
    saved = json.loads((tmp_path / "front.json").read_text())
    assert [r["name"] for r in saved["rows"]] == ["a", "b"]
    assert (tmp_path / "front.png").stat().st_size > 0 and "| a | 2 |" in (tmp_path / "front.md").read_text()


def test_front_refuses_a_missing_run_and_earlier_outputs(runs, tmp_path, capsys):
    for args in ([f"a={tmp_path / 'nope'}"], [f"a={tmp_path}"]):  # missing; a folder that is not a run
        with pytest.raises(SystemExit) as exc:
            front.main([*args, "--out", str(tmp_path)])
        assert exc.value.code == 2 and "run directory of `deliffas train`" in capsys.readouterr().err
    (tmp_path / "front.md").write_text("kept")
    with pytest.raises(SystemExit) as exc:
        front.main([f"a={runs[0]}", "--out", str(tmp_path)])
    assert exc.value.code == 2 and "--overwrite" in capsys.readouterr().err
    assert (tmp_path / "front.md").read_text() == "kept"
