"""Every command has a description and every option a help text that states its default (walks the parser)."""

from __future__ import annotations

import argparse

from deliffas.cli import build_parser


def _commands(parser: argparse.ArgumentParser, prefix: str = "deliffas"):
    yield prefix, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _commands(sub, f"{prefix} {name}")


def _takes_value(action: argparse.Action) -> bool:
    return action.nargs != 0 and not isinstance(action, (argparse._HelpAction, argparse._VersionAction,
                                                         argparse._SubParsersAction))


def test_every_option_has_help_with_its_default():
    missing = []
    for name, parser in _commands(build_parser()):
        if not parser.description:
            missing.append(f"{name}: no description")
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            flag = "/".join(action.option_strings) or action.dest
            if not action.help:
                missing.append(f"{name} {flag}: no help")
            elif _takes_value(action) and not action.required and (action.option_strings or action.nargs == "?") \
                    and "default" not in action.help:
                missing.append(f"{name} {flag}: help does not state the default")
    assert not missing, "\n".join(missing)


def test_train_help_states_the_config_defaults():
    from deliffas.engine.train_config import TrainConfig

    helps = {a.dest: a.help for a in _commands(build_parser()).__next__()[1]._subparsers._group_actions[0]
             .choices["train"]._actions}
    for dest, field in (("iters", "iters"), ("cameras_per_frame", "cameras_per_frame"), ("device", "device"),
                        ("seed", "seed"), ("checkpoint_every", "checkpoint_every"),
                        ("preview_every", "preview_every"), ("perceptual_mode", "perceptual_mode"),
                        ("perceptual", "perceptual")):
        assert f"default {TrainConfig.__dataclass_fields__[field].default}" in helps[dest], dest
    assert "default: 0 on a CPU device with 2 cores or fewer, else 1" in helps["num_workers"]


def test_os_errors_name_the_file_and_what_to_do():
    import errno
    import os

    from deliffas.cli import _error_line

    err = FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), "afile")
    assert _error_line(err) == "afile: file exists; choose another path"
    assert _error_line(FileNotFoundError("x.json: missing; pass --shards")) == "x.json: missing; pass --shards"
