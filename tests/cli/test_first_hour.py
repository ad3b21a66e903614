"""A new user's first hour (issue 30), replayed as ``deliffas`` subprocess calls on a tiny capture.

Each test is one item of the issue: runs found from another folder and after a move (1), masks that
cannot judge a calibration (2), image sizes read from the images (3), ``train --resume`` continuing the
run as it was (4), outputs checked before the work (5), Ctrl-C (6), help (7) and the smaller items (8).
The SMPL captures (items 2, 3) and the Ctrl-C of ``convert`` are marked slow.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
TRAIN = ["--preset", "tiny", "--workers", "0", "--checkpoint-every", "100", "--preview-every", "0"]


def _start(args, cwd: Path | None) -> subprocess.Popen:
    """Start ``python -m deliffas ARGS`` (one intra-op thread, as the suite)."""
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "deliffas", *map(str, args)], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _finish(proc: subprocess.Popen, check: int | None) -> subprocess.CompletedProcess:
    out, err = proc.communicate(timeout=600)
    res = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    if check is not None:
        assert res.returncode == check, f"exit {res.returncode}\n{res.stdout}\n{res.stderr}"
    return res


def deliffas(*args, cwd: Path | None = None, check: int | None = 0) -> subprocess.CompletedProcess:
    """Run ``python -m deliffas ARGS``; ``check``: the expected exit code."""
    return _finish(_start(args, cwd), check)


def deliffas_at_once(*calls: tuple[list, dict]) -> list[subprocess.CompletedProcess]:
    """Independent calls ``(ARGS, dict(cwd=..., check=...))`` run concurrently (each one's start-up, importing
    torch, is most of its time), checked as :func:`deliffas` checks them."""
    started = [(_start(args, kw.get("cwd")), kw.get("check", 0)) for args, kw in calls]
    return [_finish(proc, check) for proc, check in started]


def one_error_line(res: subprocess.CompletedProcess) -> str:
    lines = [x for x in res.stderr.splitlines() if x.strip()]
    assert res.returncode == 2 and len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    return lines[0]


@pytest.fixture(scope="module")
def home(tmp_path_factory) -> Path:
    """``a/shards`` (a tiny converted capture) and ``a/run1`` trained from inside ``a`` with relative paths."""
    from deliffas.data.convert import ConvertConfig, convert
    from deliffas.data.synth import SynthConfig, synthesize_capture
    from deliffas.geometry.procedural import ProceduralConfig, make_procedural_character

    root = tmp_path_factory.mktemp("first_hour")
    a = root / "a"
    character = make_procedural_character(ProceduralConfig(root / "character", seed=0, target_faces=2000,
                                                          texture_size=128))
    synthesize_capture(a / "subject", SynthConfig(num_frames=3, num_test_frames=1, num_cameras=3, width=32, height=32,
                                                  test_cameras=(2,), seed=0, character=str(character)))
    convert(a / "subject", a / "shards", ConvertConfig(atlas_res=32, progress=False))
    res = deliffas("train", "shards", "--out", "run1", "--iters", "2", *TRAIN, cwd=a)
    (root / "train1.stderr").write_text(res.stderr)  # item 8 reads its log
    return root


def test_1_runs_find_their_shards_from_another_folder_and_after_a_move(home, tmp_path):
    record = json.loads((home / "a" / "run1" / "train_config.json").read_text())["train"]
    assert Path(record["shards"]).is_absolute() and record["shards_from_run"] == "../shards"
    assert json.loads(deliffas("eval", "a/run1", "--json", "--max-frames", "1", cwd=home).stdout)["images"] >= 1
    moved = tmp_path / "b"
    shutil.copytree(home / "a", moved, ignore=shutil.ignore_patterns("subject"))  # run and shards move together
    shutil.move(str(home / "a" / "shards"), str(home / "shards-away"))
    try:
        found, gone = deliffas_at_once((["eval", moved / "run1", "--json", "--max-frames", "1"], {}),
                                       (["eval", home / "a" / "run1"], dict(check=2)))
        assert json.loads(found.stdout)["images"] >= 1
        line = one_error_line(gone)  # gone: say where it looked
        assert str((home / "a" / "shards").absolute()) in line and "--shards" in line
    finally:
        shutil.move(str(home / "shards-away"), str(home / "a" / "shards"))


def test_4_resume_continues_the_run_as_it_was(home, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(home / "a" / "run1", run)
    res = deliffas("train", "--resume", "--out", run)  # no --preset tiny, no --iters: the run's own
    assert "already at iteration 2" in res.stdout and "it/s" not in res.stdout
    line = one_error_line(deliffas("train", "--resume", "--out", run, "--preset", "small", check=2))
    assert "--preset" in line and "'tiny'" in line and "'small'" in line
    res = deliffas("train", "--resume", "--out", run, "--iters", "3", "--workers", "0")
    assert "to iteration 3" in res.stdout
    state = json.loads((run / "train_state.json").read_text())
    assert state["iteration"] == 3 and json.loads((run / "train_config.json").read_text())["train"]["preset"] == "tiny"


def test_5_outputs_are_checked_before_the_work(home):
    *unwritable, res = deliffas_at_once(
        (["eval", "a/run1", "--grid", "/sys/deliffas-test/g.png"], dict(cwd=home, check=2)),
        (["render", "a/run1", "--out", "/sys/deliffas-test/v.mp4"], dict(cwd=home, check=2)),
        (["convert", home / "a" / "subject", home / "x", "--atlas-res", "50"], dict(check=2)))
    for out in unwritable:
        line = one_error_line(out)
        assert "/sys/deliffas-test/" in line and "cannot write" in line, line
    assert "power of two" in res.stderr and not (home / "x").exists()


def _interrupt(args: list, cwd: Path, when) -> subprocess.CompletedProcess:
    """Start ``deliffas ARGS`` in its own process group, send the group SIGINT (Ctrl-C) once ``when(stderr so far)``."""
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    err_path = cwd / "stderr.txt"
    with open(err_path, "w") as err:
        p = subprocess.Popen([sys.executable, "-m", "deliffas", *map(str, args)], cwd=cwd, env=env, text=True,
                             stdout=subprocess.PIPE, stderr=err, start_new_session=True)
        t0 = time.time()
        while p.poll() is None and not when(err_path.read_text(), time.time() - t0):
            time.sleep(0.1)
        try:
            os.killpg(p.pid, signal.SIGINT)
        except ProcessLookupError:  # the command (and its group) ended first: a fast machine finished the work
            pass
        out, _ = p.communicate(timeout=300)
    return subprocess.CompletedProcess(p.args, p.returncode, out, err_path.read_text())


def test_6_ctrl_c_in_train_keeps_the_iteration_and_says_how_to_resume(home, tmp_path):
    shutil.copytree(home / "a" / "shards", tmp_path / "shards")
    res = _interrupt(["train", "shards", "--out", "run", "--iters", "1000", *TRAIN], tmp_path,
                     lambda err, t: "3/1000" in err or t > 240)
    assert res.returncode == 130 and "Traceback" not in res.stderr, res.stderr
    done = json.loads((tmp_path / "run" / "train_state.json").read_text())["iteration"]
    assert 3 <= done < 100  # the interrupted iteration, not the last periodic checkpoint (none yet)
    assert f"checkpoint at iteration {done} kept" in res.stderr
    assert "resume with: deliffas train --resume --out run" in res.stderr


@pytest.mark.slow
@pytest.mark.parametrize("after_s", [0.5, 3.0, None])
def test_6_ctrl_c_in_convert_at_any_moment(home, tmp_path, after_s):
    args = ["convert", home / "a" / "subject", "out", "--atlas-res", "32", "--shard-frames", "1", "--no-progress"]
    res = _interrupt(args, tmp_path, lambda err, t: (t > after_s if after_s is not None else
                                                      (tmp_path / "out" / "manifest.json").is_file()))
    assert res.returncode in (130, 0) and "Traceback" not in res.stderr, res.stderr
    if res.returncode == 130:
        assert "resume with: deliffas convert" in res.stderr and res.stderr.rstrip().endswith("--resume")


_INTERRUPT_ON_IMPORT = """
import importlib.abc, os, signal, sys

class _Interrupt(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == os.environ["DELIFFAS_TEST_INTERRUPT_ON_IMPORT"]:
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
        return None

sys.meta_path.insert(0, _Interrupt())
"""


@pytest.mark.parametrize("module", ["argparse", "deliffas.cli.handlers", "torch"])
def test_6_ctrl_c_while_the_console_script_starts(tmp_path, module):
    """Ctrl-C while the ``deliffas`` console script imports MODULE (a sitecustomize sends it then): one line, 130.

    Python's own start-up (its codecs, ``site`` and ``.pth`` files) runs before any line of the package and
    stays out of reach; this covers every import from the console script's first line on.
    """
    scripts = (REPO / "pyproject.toml").read_text().split("[project.scripts]")[1]
    module_name, func = re.search(r'^deliffas = "([\w.]+):(\w+)"', scripts, re.M).groups()
    (tmp_path / "sitecustomize.py").write_text(_INTERRUPT_ON_IMPORT)
    console_script = f"import sys\nfrom {module_name} import {func}\nsys.exit({func}())\n"  # as pip writes it
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]), OMP_NUM_THREADS="1",
               DELIFFAS_TEST_INTERRUPT_ON_IMPORT=module)
    res = subprocess.run([sys.executable, "-c", console_script, "convert", "capture", "out"], cwd=tmp_path,
                         env=env, text=True, capture_output=True, timeout=300)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 130 and len(lines) == 1, res.stderr
    assert lines[0].startswith("deliffas convert: interrupted") and lines[0].endswith(
        "resume with: deliffas convert capture out --resume"), lines[0]


_INTERRUPT_IN_A_FINALISER = """
import importlib.abc, os, signal, sys

class _SendsCtrlCWhenCollected:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGINT)  # its KeyboardInterrupt is raised here, in a finaliser: unraisable

class _Interrupt(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "deliffas.data.convert":
            sys.meta_path.remove(self)
            _SendsCtrlCWhenCollected()
        return None

sys.meta_path.insert(0, _Interrupt())
"""


def test_6_ctrl_c_that_lands_in_a_finaliser_still_interrupts(tmp_path):
    """A Ctrl-C whose KeyboardInterrupt Python raises in a finaliser or weakref callback (importlib's module locks
    have them), where it cannot propagate: still one line and 130, not a printed traceback and a command that
    carries on."""
    (tmp_path / "sitecustomize.py").write_text(_INTERRUPT_IN_A_FINALISER)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]), OMP_NUM_THREADS="1")
    res = subprocess.run([sys.executable, "-m", "deliffas", "convert", "capture", "out"], cwd=tmp_path, env=env,
                         text=True, capture_output=True, timeout=300)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 130 and len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    assert lines[0].startswith("deliffas convert: interrupted"), lines[0]


_INTERRUPT_AT_EXIT = """
import atexit, os, signal

def _ctrl_c_at_exit():
    with open("sigint_at_exit.txt", "w") as f:  # what a Ctrl-C later in the exit meets (Python keeps SIG_IGN)
        f.write(str(signal.getsignal(signal.SIGINT) is signal.SIG_IGN))
    os.kill(os.getpid(), signal.SIGINT)

atexit.register(_ctrl_c_at_exit)
"""


def test_6_ctrl_c_after_the_command_ended_keeps_its_exit_code(tmp_path):
    """A Ctrl-C that lands while the interpreter exits, after the command's work and its report: the command's own
    exit code and no traceback, not the signal's exit (-2: Python restores the default handler late in its exit),
    which would tell a script that the work did not finish."""
    (tmp_path / "sitecustomize.py").write_text(_INTERRUPT_AT_EXIT)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(REPO)]), OMP_NUM_THREADS="1")
    res = subprocess.run([sys.executable, "-m", "deliffas", "convert", "capture", "out"], cwd=tmp_path, env=env,
                         text=True, capture_output=True, timeout=300)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert (tmp_path / "sigint_at_exit.txt").read_text() == "True"


def test_7_help_states_defaults():
    from deliffas.engine.train_config import TrainConfig

    out = " ".join(deliffas("train", "--help").stdout.split())
    for text in (f"default {TrainConfig.iters}", f"default {TrainConfig.cameras_per_frame}", "default cpu",
                 "0 on a CPU device with 2 cores or fewer, else 1)", "default 0", "default 250"):
        assert text in out, text
    assert "realtime" in (REPO / "README.md").read_text().split("deliffas zoo list")[1].split("\n")[0]


def test_8_smaller_items(home):
    verify, zoo, view, render = deliffas_at_once(
        (["verify", home / "nonexistent"], dict(check=2)),
        (["zoo", "list"], {}),
        (["view", "a/run1", "--shards", "a/nonexistent"], dict(cwd=home, check=2)),
        (["render", "a/run1", "--out", "v", "--orbit"], dict(cwd=home)))
    one_error_line(verify)
    rows = [re.match(r"\S+\s+\S+\s+\d+", r) for r in zoo.stdout.splitlines()]
    assert len({m.end() for m in rows if m}) == 1  # the S column lines up, on 'realtime' too
    assert "http://" not in view.stdout
    train_log = (home / "train1.stderr").read_text()  # the fixture's `train shards --out run1` (protocol auto)
    assert "WARNING" not in train_log and "frames protocol auto -> all" in train_log
    assert "--frames 100 --loop" in render.stderr


@pytest.fixture(scope="module")
def easymocap_without_masks_or_sizes(tmp_path_factory) -> Path:
    """An EasyMocap capture as EasyMocap writes it: no H_/W_ in intri.yml; and no mask/ folder."""
    from deliffas.data.export_capture import export_capture
    from deliffas.data.subjects import parse_subject
    from deliffas.data.synth import SynthConfig, synthesize_capture

    root = tmp_path_factory.mktemp("easymocap")
    synthesize_capture(root / "smpl", SynthConfig(num_frames=2, num_test_frames=1, num_cameras=3, width=48, height=48,
                                                  seed=1, body_model="procedural", fps=3.0))
    cap = export_capture(parse_subject(root / "smpl"), root / "cap", "easymocap", jpeg_quality=100)
    shutil.rmtree(cap / "mask")
    intri = cap / "intri.yml"
    intri.write_text("\n".join(x for x in intri.read_text().splitlines() if not x.startswith(("H_", "W_"))) + "\n")
    return cap


@pytest.mark.slow
def test_2_missing_masks_are_named_and_no_units_fix_is_proposed(easymocap_without_masks_or_sizes, tmp_path):
    cap = easymocap_without_masks_or_sizes
    model = cap.parent / "smpl" / "body" / "smpl_procedural.npz"
    res, refused = deliffas_at_once((["check", cap, "--out", tmp_path / "report", "--template", model], dict(check=1)),
                                    (["convert", cap, tmp_path / "out", "--template", model], dict(check=2)))
    assert "masks missing or all foreground" in res.stdout and "1000" not in res.stdout
    assert "--no-check" not in res.stdout  # an option of convert, not of check
    line = one_error_line(refused)
    assert "masks missing or all foreground" in line and "1000" not in line and "--no-check" in line


@pytest.mark.slow
def test_3_sizes_from_the_images(easymocap_without_masks_or_sizes, tmp_path):
    from deliffas.io.camera_formats import read_cameras

    empty = tmp_path / "bare"  # the calibration without its images
    empty.mkdir()
    shutil.copy(easymocap_without_masks_or_sizes / "intri.yml", empty)
    shutil.copy(easymocap_without_masks_or_sizes / "extri.yml", empty)
    _, refused = deliffas_at_once(
        (["cameras", easymocap_without_masks_or_sizes, tmp_path / "c.calibration", "--to", "dynacap"], {}),
        (["cameras", empty, tmp_path / "d.calibration", "--to", "dynacap"], dict(check=2)))
    assert {(c.width, c.height) for c in read_cameras(tmp_path / "c.calibration")} == {(48, 48)}
    line = one_error_line(refused)
    assert "--size WxH" in line and "size=" not in line
