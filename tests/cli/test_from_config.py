"""The argparse options generated from config fields (``deliffas.cli.from_config``), and the handlers using them."""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pytest

from deliffas.cli.from_config import add_config_arguments, config_from_args, given_values, option_names
from deliffas.options import image_size, opt, positive_int

REPO = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Toy:
    """A config with one field of each kind the generator handles."""

    src: str = opt(help="input folder", flag="")
    out: str = opt(help="output folder")
    iters: int = opt(100, help="iterations", parse=positive_int)
    rate: float = opt(0.5, help="step size")
    mode: Literal["fast", "exact"] = opt("fast", help="how to run")
    size: tuple[int, int] | None = opt(None, help="WxH", parse=image_size, default_text="the input's")
    workers: int = opt(1, help="processes", flag="--jobs")
    loud: bool = opt(False, help="say more")
    progress: bool = opt(True, help="no progress bar")
    tags: tuple[str, ...] = opt((), help="a tag (repeatable)", repeat=True, default_text="none")
    name: str | None = opt(None, help="a name", default_text="the folder's")
    hidden: int = 7
    """Not on the command line (no ``opt``)."""


def _parser(sparse: bool = False) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toy")
    add_config_arguments(p, Toy, sparse=sparse)
    return p


def _actions(p: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {a.dest: a for a in p._actions if a.dest != "help"}


def test_one_option_per_field_with_its_spelling_type_and_choices():
    acts = _actions(_parser())
    assert set(acts) == {"src", "out", "iters", "rate", "mode", "size", "workers", "loud", "progress", "tags", "name"}
    assert acts["src"].option_strings == [] and acts["out"].required and acts["out"].option_strings == ["--out"]
    assert acts["workers"].option_strings == ["--jobs"] and acts["workers"].metavar == "JOBS"
    assert acts["iters"].type is positive_int
    assert acts["rate"].type is float and acts["mode"].choices == ["fast", "exact"]
    assert acts["loud"].option_strings == ["--loud"] and acts["loud"].nargs == 0
    assert acts["progress"].option_strings == ["--no-progress"] and acts["progress"].default is True
    assert option_names(Toy)["workers"] == "--jobs" and option_names(Toy)["src"] == "SRC"
    assert option_names(Toy)["progress"] == "--no-progress"


def test_help_states_each_default():
    acts = _actions(_parser())
    assert acts["iters"].help == "iterations (default 100)"
    assert acts["mode"].help == "how to run (default fast)"
    assert acts["size"].help == "WxH (default: the input's)"
    assert acts["loud"].help == "say more"  # an on/off flag: its absence is the default
    assert "default" not in acts["out"].help  # required


def test_namespace_round_trips_to_the_config():
    args = _parser().parse_args(["in", "--out", "o", "--iters", "3", "--mode", "exact", "--size", "4x2", "--loud",
                                 "--no-progress", "--tags", "a", "--tags", "b", "--jobs", "2"])
    cfg = config_from_args(Toy, args, hidden=9)
    assert cfg == Toy(src="in", out="o", iters=3, rate=0.5, mode="exact", size=(4, 2), workers=2, loud=True,
                      progress=False, tags=("a", "b"), name=None, hidden=9)
    assert config_from_args(Toy, _parser().parse_args(["in", "--out", "o"])) == Toy(src="in", out="o")


def test_sparse_options_are_none_unless_given_and_still_state_the_default():
    p = _parser(sparse=True)
    assert given_values(Toy, p.parse_args(["in", "--out", "o", "--iters", "5"])) == {"src": "in", "out": "o",
                                                                                    "iters": 5}
    assert _actions(p)["iters"].default is None and _actions(p)["iters"].help == "iterations (default 100)"


def test_bad_values_are_argparse_errors(capsys):
    with pytest.raises(SystemExit) as exc:
        _parser().parse_args(["in", "--out", "o", "--iters", "0"])
    assert exc.value.code == 2 and "expected a number >= 1, got 0" in capsys.readouterr().err


def test_path_annotations_and_choices_asked_when_the_parser_is_built():
    names = ["a"]

    @dataclass(frozen=True)
    class Files:
        src: Path = opt(help="input", flag="")
        kind: str = opt("a", help="a registered kind", choices=lambda: tuple(names))

    names.append("b")  # registered after the config was declared: the parser still offers it
    p = argparse.ArgumentParser()
    add_config_arguments(p, Files)
    assert config_from_args(Files, p.parse_args(["x/y", "--kind", "b"])) == Files(src=Path("x/y"), kind="b")
    assert _actions(p)["kind"].choices == ["a", "b"] and _actions(p)["kind"].help == "a registered kind (default a)"


def test_a_default_of_none_must_say_what_it_means():
    @dataclass(frozen=True)
    class Mute:
        x: int | None = opt(None, help="x")

    with pytest.raises(TypeError, match="default_text"):
        add_config_arguments(argparse.ArgumentParser(), Mute)


def test_an_annotation_without_a_parser_is_refused():
    @dataclass(frozen=True)
    class Odd:
        x: dict = opt(default_factory=dict, help="x", default_text="empty")

    with pytest.raises(TypeError, match="parse"):
        add_config_arguments(argparse.ArgumentParser(), Odd)


GENERATED = {"cmd_train": "TrainConfig", "cmd_eval": "EvalConfig", "cmd_render": "RenderConfig",
             "cmd_convert": "ConvertConfig", "cmd_synth": "SynthConfig", "cmd_check": "CheckConfig",
             "cmd_demo": "DemoConfig", "cmd_view": "ViewConfig", "cmd_export": "ExportConfig",
             "cmd_verify": "VerifyConfig", "cmd_pose": "PoseConfig", "cmd_character_procedural": "ProceduralConfig",
             "cmd_template": "TemplateConfig", "cmd_zoo": "ZooConfig",
             "cmd_cameras": "CamerasConfig", "cmd_fit_smpl": "FitSmplConfig"}
"""Each config command's handler and the config its options are generated from."""


def _handlers() -> dict[str, ast.FunctionDef]:
    tree = ast.parse((REPO / "deliffas" / "cli" / "handlers.py").read_text())
    return {n.name: n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}


def _calls(fn: ast.FunctionDef, handlers: dict[str, ast.FunctionDef]) -> set[str]:
    """Names called in ``fn`` and in the handlers' helpers it calls."""
    names = {n.func.id for n in ast.walk(fn) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    for helper in [h for h in names if h.startswith("_") and h in handlers]:
        names |= _calls(handlers[helper], handlers)
    return names


def test_config_handlers_build_their_config_by_the_generator():
    handlers = _handlers()
    for name, config in GENERATED.items():
        calls = _calls(handlers[name], handlers)
        assert calls & {"config_from_args", "given_values"}, f"{name} does not build {config} by the generator"


def test_no_handler_passes_namespace_attributes_as_config_fields():
    """``SomeConfig(x=args.x, ...)``: the per-field mapping the generator replaces."""
    mapped = []
    for name, fn in _handlers().items():
        for call in (n for n in ast.walk(fn) if isinstance(n, ast.Call)):
            callee = call.func.id if isinstance(call.func, ast.Name) else ""
            if callee in GENERATED.values():
                fields = [k.arg for k in call.keywords if isinstance(k.value, ast.Attribute)
                          and isinstance(k.value.value, ast.Name) and k.value.value.id == "args"]
                if fields:
                    mapped.append(f"{name}: {callee}({', '.join(fields)})")
    assert not mapped, mapped


HAND_WRITTEN = {
    "build_parser -v": "global: the log level, before any command",
    "build_parser --version": "global",
    "_synth_out_dir out_dir": "synth: synthesize_capture(out_dir, SynthConfig)'s path, not a config field",
    "_synth_size --size": "synth: one option setting two fields, SynthConfig.width and height",
    "_convert_paths subject": "convert: convert(subject, out, ConvertConfig)'s paths, not config fields",
    "_convert_paths out": "convert: as SUBJECT",
    "_train_options --config": "train: a JSON file of TrainConfig fields, read before the options",
    "_train_options --resume": "train: Trainer(resume=); also changes how the config is built",
    "_train_options --overwrite": "train: Trainer(overwrite=)",
    "_train_options --auto-capacity": "train: calls auto_capacity() instead of Trainer",
    "_eval_options --json": "eval: how the result is printed",
    "_eval_options --fast": "eval: deprecated alias of --render-path fast (one release)",
    "_plain_option --plain": "render and view: deprecated alias of --render-path plain (one release)",
}
"""The options still declared by hand in ``deliffas/cli/__init__.py`` and the command table ``deliffas/cli/commands.py``
(function, spelling) and why: none sets a config field one to one."""


def test_options_are_declared_by_hand_only_where_no_config_field_fits():
    trees = [ast.parse((REPO / "deliffas" / "cli" / name).read_text()) for name in ("__init__.py", "commands.py")]
    found = sorted(f"{fn.name} {call.args[0].value}" for tree in trees for fn in ast.walk(tree)
                   if isinstance(fn, ast.FunctionDef) for call in ast.walk(fn)
                   if isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute) and call.func.attr == "add_argument")
    assert found == sorted(HAND_WRITTEN), "declare the option as an opt() field of the command's config"


def test_help_imports_no_torch():
    code = ("import sys; from deliffas.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('torch', 'h5py', 'open3d') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}).stdout
    assert out.strip() == "[]"


@dataclass(frozen=True)
class Inner:
    """A config nested in another (as ``RenderPathConfig`` in ``EvalConfig``)."""

    way: Literal["a", "b"] = opt("a", help="which way", flag="--way")
    on: bool = opt(True, help="switch", flag="--switch")
    count: int = opt(0, help="how many", parse=positive_int)


@dataclass(frozen=True)
class Outer:
    src: str = opt(help="input", flag="")
    inner: Inner = opt(Inner(way="b", on=False), help="the inner settings")


def test_a_nested_config_is_flattened_into_a_group_with_the_outer_default():
    p = argparse.ArgumentParser()
    add_config_arguments(p, Outer)
    acts = _actions(p)
    assert set(acts) == {"src", "inner.way", "inner.on", "inner.count"}
    assert acts["inner.way"].help == "which way (default b)"  # the outer field's default, not Inner's
    assert acts["inner.on"].option_strings == ["--switch", "--no-switch"]
    assert acts["inner.on"].help == "switch (default off)"
    assert acts["inner.count"].option_strings == ["--count"] and all(a.default is None for a in acts.values())
    assert any(g.title == "inner" and g.description == "the inner settings" for g in p._action_groups)
    assert config_from_args(Outer, p.parse_args(["x"])) == Outer(src="x")
    assert config_from_args(Outer, p.parse_args(["x", "--switch", "--count", "3"])) == \
        Outer(src="x", inner=Inner(way="b", on=True, count=3))  # the options not given keep the outer default
    assert config_from_args(Outer, p.parse_args(["x", "--way", "a", "--no-switch"])).inner == Inner(way="a", on=False)
    assert option_names(Outer) == {"src": "SRC", "inner.way": "--way", "inner.on": "--switch",
                                   "inner.count": "--count"}


def _parse(argv: list[str]) -> argparse.Namespace:
    from deliffas.cli import build_parser

    return build_parser().parse_args(argv)


def test_render_path_options_per_command(tmp_path):
    from deliffas.engine.eval_config import EvalConfig
    from deliffas.engine.render_config import RenderConfig
    from deliffas.engine.view_config import ViewConfig
    from deliffas.fast.config import RenderPathConfig

    video = ["render", "RUN", "--out", str(tmp_path / "v.mp4")]
    assert config_from_args(EvalConfig, _parse(["eval", "RUN"])).render_path == RenderPathConfig(path="plain")
    assert config_from_args(RenderConfig, _parse(video)).render_path == RenderPathConfig(project_features=False)
    assert config_from_args(ViewConfig, _parse(["view", "RUN"])).render_path == RenderPathConfig()
    got = config_from_args(RenderConfig, _parse([*video, "--render-path", "plain", "--uv", "raycast"])).render_path
    assert got == RenderPathConfig(path="plain", uv="raycast", project_features=False)
    got = config_from_args(EvalConfig, _parse(["eval", "RUN", "--render-path", "fast", "--render-dtype", "float32",
                                               "--no-fused-shade", "--no-pe-table", "--frames-in-flight", "1"]))
    assert got.render_path == RenderPathConfig(dtype="float32", fused=False, pe_table=False, in_flight=1)
    got = config_from_args(ViewConfig, _parse(["view", "RUN", "--no-project-features"])).render_path
    assert got == RenderPathConfig(project_features=False)
    assert config_from_args(RenderConfig, _parse([*video, "--project-features"])).render_path == RenderPathConfig()


def test_render_path_help_states_each_commands_default():
    from deliffas.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    helps = {name: {a.option_strings[0]: a.help for a in sub.choices[name]._actions if a.option_strings}
             for name in ("eval", "render", "view")}
    assert helps["eval"]["--render-path"].endswith("(default plain)")
    assert helps["render"]["--render-path"].endswith("(default fast)")
    assert helps["render"]["--project-features"].endswith("(default off)")
    assert helps["view"]["--project-features"].endswith("(default on)")
    assert helps["view"]["--uv"].endswith("(default auto)")
    assert helps["eval"]["--fast"] == "deprecated: --render-path fast"


@pytest.mark.parametrize("argv", [["eval", "RUN"], ["render", "RUN", "--out", "v.mp4"], ["view", "RUN"]])
def test_a_bad_render_path_value_exits_2_naming_the_choices(argv, capsys):
    for bad, named in ((["--uv", "gpu"], "'auto', 'raster', 'raycast', 'torch'"),
                       (["--render-path", "slow"], "'fast', 'plain'"),
                       (["--frames-in-flight", "-1"], "expected a number >= 0")):
        with pytest.raises(SystemExit) as exc:
            _parse([*argv, *bad])
        assert exc.value.code == 2 and named in capsys.readouterr().err


def test_the_deprecated_path_flags_still_work_and_warn(tmp_path, caplog, monkeypatch):
    import logging

    from deliffas.cli import handlers, main
    from deliffas.engine.eval_config import EvalConfig
    from deliffas.engine.render_config import RenderConfig
    from deliffas.engine.view_config import ViewConfig

    video = ["render", "RUN", "--out", str(tmp_path / "v.mp4")]
    assert config_from_args(RenderConfig, _parse([*video, "--plain"])).render_path.path == "plain"
    assert config_from_args(ViewConfig, _parse(["view", "RUN", "--plain"])).render_path.path == "plain"
    args = _parse(["eval", "RUN", "--fast"])
    assert config_from_args(EvalConfig, args).render_path.path == "fast" and "--render-path fast" in args.deprecated[0]
    seen = []
    monkeypatch.setattr(handlers, "cmd_render", lambda a: seen.append(config_from_args(RenderConfig, a)) or 0)
    with caplog.at_level(logging.WARNING, logger="deliffas.cli"):
        assert main([*video, "--plain"]) == 0
    assert seen[0].render_path.path == "plain"
    assert any("--plain is deprecated" in r.getMessage() and "--render-path plain" in r.getMessage()
               for r in caplog.records)


def test_check_fields_refuses_in_python_what_the_option_refuses():
    """One check per option, declared on the field: ``check_fields`` runs its ``parse`` and ``Literal`` on the value
    a config was built with, so Python and the command line refuse the same values with the field's name."""
    from dataclasses import dataclass
    from typing import Literal

    from deliffas.options import check_fields, opt, positive_float, positive_int

    @dataclass(frozen=True)
    class Config:
        steps: int = opt(3, help="steps", parse=positive_int)
        scale: float | None = opt(None, help="scale", parse=positive_float)
        mode: Literal["a", "b"] | None = opt("a", help="mode")
        sizes: tuple[int, ...] = opt((1, 2), help="sizes")

        def __post_init__(self) -> None:
            check_fields(self)

    Config(), Config(steps=1, scale=None, mode=None, sizes=())
    for kwargs, message in ((dict(steps=0), "steps: expected a number >= 1"), (dict(steps=True), "steps: expected int"),
                            (dict(scale=float("nan")), "scale: expected a positive finite number"),
                            (dict(mode="c"), "mode: expected one of a, b")):
        with pytest.raises(ValueError, match=message):
            Config(**kwargs)
