"""TrainConfig.schedule: the hold-decay and converge schedules (warm-up, decay over the run) and the paper's."""

from __future__ import annotations

import math

import pytest

from deliffas.engine.train_config import SCHEDULE_BETA2, SCHEDULE_LR, TrainConfig


def _cfg(**kw) -> TrainConfig:
    return TrainConfig(shards="s", out="o", **kw)


@pytest.mark.parametrize("schedule", ["hold-decay", "converge"])
def test_the_run_long_schedules_warm_up_then_decay_to_lr_final_at_the_last_iteration(schedule):
    cfg = _cfg(schedule=schedule, iters=1000, warmup_iters=50, lr_final=0.1)
    assert cfg.peak_lr == SCHEDULE_LR[schedule]
    assert cfg.lr_at(0) == pytest.approx(cfg.peak_lr / 50)
    assert cfg.lr_at(49) == pytest.approx(cfg.peak_lr)
    assert cfg.lr_at(50) == pytest.approx(cfg.peak_lr)
    assert cfg.lr_at(999) == pytest.approx(0.1 * cfg.peak_lr)
    lrs = [cfg.lr_at(i) for i in range(50, 1000)]
    assert all(a >= b for a, b in zip(lrs, lrs[1:]))


def test_hold_decay_is_the_default_and_holds_the_peak_before_its_decay():
    cfg, converge = _cfg(iters=1051), _cfg(iters=1051, schedule="converge")  # 1000 iterations after the warm-up
    assert cfg.schedule == "hold-decay"
    assert cfg.lr_at(50) == cfg.lr_at(749) == cfg.peak_lr  # held for 70 % of them
    assert cfg.lr_at(900) / cfg.peak_lr == pytest.approx(0.1 ** 0.5)  # halfway through the decay
    assert cfg.lr_at(1050) == pytest.approx(0.1 * cfg.peak_lr)
    assert converge.lr_at(550) / converge.peak_lr == pytest.approx(0.1 ** 0.5)  # converge: halfway through the run
    lrs = [cfg.lr_at(i) for i in range(50, 1051)]
    assert all(a >= b for a, b in zip(lrs, lrs[1:]))


@pytest.mark.parametrize("schedule", ["hold-decay", "converge", "paper"])
def test_each_schedule_has_its_adam_beta2_and_an_explicit_one_wins(schedule):
    from deliffas.engine.train import make_optimizer
    from deliffas.models.deliffas import DeliffasModel
    from deliffas.models.zoo import get_config

    model = DeliffasModel(get_config("two_surface", "tiny"))
    for beta2, expected in ((None, SCHEDULE_BETA2[schedule]), (0.9, 0.9)):
        cfg = _cfg(schedule=schedule, adam_beta2=beta2)
        assert cfg.beta2 == expected
        assert all(g["betas"] == (0.9, expected) for g in make_optimizer(model, cfg).param_groups)


def test_a_run_recorded_before_adam_beta2_resumes_with_its_beta2_and_refuses_another(tiny_shards, tmp_path):
    import json

    from deliffas.engine.resume import resumed_config
    from deliffas.engine.train import train

    run = tmp_path / "r"
    train(TrainConfig(shards=str(tiny_shards), out=str(run), schedule="converge", model="two_surface", preset="tiny",
                      iters=2, cameras_per_frame=2, protocol="all", num_workers=0, preview_every=0, progress=False))
    path = run / "train_config.json"
    record = json.loads(path.read_text())
    assert record["train"].pop("adam_beta2") is None and record["train"].pop("decay_share") == 0.3
    path.write_text(json.dumps(record))
    assert resumed_config(run, {}).beta2 == 0.999
    with pytest.raises(ValueError, match="adam_beta2"):
        resumed_config(run, {"adam_beta2": 0.9})


def test_warmup_is_at_most_a_fifth_of_a_short_run():
    cfg = _cfg(iters=10, warmup_iters=50)
    assert cfg.lr_at(1) == pytest.approx(cfg.peak_lr)  # 2 warm-up iterations
    assert cfg.lr_at(9) == pytest.approx(cfg.peak_lr * cfg.lr_final)


def test_paper_schedule_is_the_official_decay():
    cfg = _cfg(schedule="paper", iters=10)
    assert cfg.peak_lr == 2e-4
    assert cfg.lr_at(400_000) == pytest.approx(2e-4 * math.sqrt(0.1))
    assert _cfg(schedule="paper", lr=1e-3).lr_at(0) == 1e-3


@pytest.mark.parametrize("field,value", [("lr", 0.0), ("lr", float("nan")), ("lr_final", 0.0), ("lr_final", 2.0),
                                         ("warmup_iters", -1), ("adam_beta2", 1.0), ("adam_beta2", 0.0),
                                         ("decay_share", 0.0), ("decay_share", 1.5)])
def test_bad_schedule_values_are_refused_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        _cfg(**{field: value})


def _resumes_after_editing_its_groups(shards, run, edit) -> bool:
    """Train 2 iterations, pass the saved optimizer groups through ``edit``, resume to 3."""
    import json

    from deliffas.engine.checkpointing import STATE_FILE
    from deliffas.engine.train import train

    kw = dict(shards=str(shards), out=str(run), model="two_surface", preset="tiny", cameras_per_frame=2,
              protocol="all", num_workers=0, checkpoint_every=1, preview_every=0, progress=False)
    train(TrainConfig(iters=2, **kw))
    path = run / STATE_FILE
    state = json.loads(path.read_text())
    edit(state["optimizer_param_groups"])
    path.write_text(json.dumps(state))
    return train(TrainConfig(iters=3, **kw), resume=True).iterations == 3


def test_a_run_saved_before_the_rate_multiples_resumes(tiny_shards, tmp_path):
    """Optimizer groups loaded from an older run's state lack ``lr_scale``; the config's multiples apply."""
    def drop_scales(groups):
        for group in groups:
            del group["lr_scale"]

    assert _resumes_after_editing_its_groups(tiny_shards, tmp_path / "run", drop_scales)


def test_a_run_saved_with_the_per_tensor_adam_resumes(tiny_shards, tmp_path):
    """Runs saved before the fused Adam (``fused`` None in their groups) resume, and a new run uses it."""
    def unfuse(groups):
        assert all(group["fused"] for group in groups)
        for group in groups:
            group["fused"] = None

    assert _resumes_after_editing_its_groups(tiny_shards, tmp_path / "run", unfuse)


@pytest.mark.parametrize("cores, workers", [(1, 0), (2, 0), (4, 1), (None, 0)])
def test_data_workers_default_to_the_process_on_two_cpu_cores(monkeypatch, cores, workers):
    monkeypatch.setattr("os.cpu_count", lambda: cores)
    assert TrainConfig(shards="s", out="o").data_workers == workers
    assert TrainConfig(shards="s", out="o", num_workers=3).data_workers == 3
