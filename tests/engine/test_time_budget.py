"""``TrainConfig.time_budget``: a run sized by time fixes its length after the first iterations and records it."""

from __future__ import annotations

import json

import pytest

from deliffas.cli import main
from deliffas.engine.resume import resumed_config
from deliffas.engine.train import TrainConfig, train
from deliffas.engine.time_budget import CALIBRATION, MARGIN, MIN_LEFT, UNTIMED, BudgetPlanner, budgeted_iters


def test_budgeted_iters_adds_what_fits_in_the_time_left_with_the_margin():
    assert budgeted_iters(40, 0.1, 100.0) == 40 + int(MARGIN * 1000)
    assert budgeted_iters(40, 0.1, -5.0) == 40  # the timing itself took the budget: the run stops there
    with pytest.raises(ValueError, match="seconds_per_iteration"):
        budgeted_iters(40, 0.0, 10.0)


def test_the_planner_times_after_the_start_up_and_plans_again_at_the_later_speed():
    planner = BudgetPlanner(seconds=100.0, created=0.0, start=0)
    clock = {n: 1.0 + 0.1 * n for n in range(CALIBRATION + 1)}  # 0.1 s per iteration from the start
    plans = [planner.after(n, clock[n]) for n in range(1, CALIBRATION + 1)]
    assert plans[:-1] == [None] * (CALIBRATION - 1)
    first = plans[-1]
    assert first == budgeted_iters(CALIBRATION, 0.1, 100.0 - clock[CALIBRATION])
    assert planner.next_plan == CALIBRATION + (first - CALIBRATION) // 2
    # the machine slows to 0.2 s per iteration: the next plan fits fewer
    at = planner.next_plan
    t = clock[CALIBRATION] + 0.2 * (at - CALIBRATION)
    second = planner.after(at, t)
    assert second == budgeted_iters(at, 0.2, 100.0 - t) and second < first
    assert planner.record()["iterations"] == second and len(planner.record()["plans"]) == 2
    assert UNTIMED < CALIBRATION and MIN_LEFT > 0


@pytest.mark.parametrize("kw,match", [({"time_budget": 0.0}, "time_budget: expected"),
                                      ({"time_budget": float("inf")}, "time_budget: expected"),
                                      ({"time_budget": 60.0, "perceptual": "vgg16-random"}, "give --iters")])
def test_bad_time_budgets_are_refused_when_the_run_is_described(kw, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig(shards="s", out="o", **kw)


def test_a_budgeted_run_fixes_its_length_decays_over_it_and_resumes_as_it_was(tiny_shards, tmp_path):
    run = tmp_path / "run"
    cfg = TrainConfig(shards=str(tiny_shards), out=str(run), model="two_surface", preset="tiny", iters=5,
                      time_budget=4.0, cameras_per_frame=2, protocol="all", num_workers=0, checkpoint_every=1000,
                      preview_every=0, log_every=1, progress=False)
    result = train(cfg)
    record = json.loads((run / "train_config.json").read_text())
    n = result.iterations
    assert n >= CALIBRATION  # at least the timed iterations, whatever --iters said
    assert record["train"]["iters"] == n and record["train"]["time_budget"] is None
    assert record["time_budget"]["iterations"] == n and record["time_budget"]["seconds"] == 4.0
    assert record["time_budget"]["plans"][0]["at_iteration"] == CALIBRATION
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert log[-1]["iteration"] == n
    assert log[-1]["lr"] == pytest.approx(cfg.peak_lr * cfg.lr_final)  # the decay ends at the resolved length
    resumed = resumed_config(run, {})
    assert resumed.iters == n and resumed.time_budget is None  # a resumed run is not sized again


def test_the_command_line_refuses_iters_and_a_time_budget_together(tiny_shards, tmp_path, capsys):
    code = main(["train", str(tiny_shards), "--out", str(tmp_path / "run"), "--iters", "5", "--time-budget", "9"])
    assert code == 2 and "give --iters or --time-budget, not both" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_planners_that_agree_on_a_length_plan_again_at_the_same_iteration():
    """Under DDP each rank times itself but follows rank 0's plan: the next plan must fall on the same iteration."""
    fast, slow = (BudgetPlanner(seconds=100.0, created=0.0, start=0) for _ in range(2))
    for n in range(1, CALIBRATION + 1):
        first = fast.after(n, 0.1 * n)
        second = slow.after(n, 0.3 * n, agree=lambda _, first=first: first)  # rank 0's value, as broadcast
    assert second == first and slow.next_plan == fast.next_plan is not None
