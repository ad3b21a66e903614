"""Fixtures of the reliability suite: one tiny capture per session, its reference conversion, counters.

The capture is built once (procedural character, 4 cameras at 48 x 48, 12 training + 2 testing
frames) and treated as read-only: tests that write copy it or write elsewhere under tmp_path.
The reference conversion (in-process, uninterrupted) is what every crashed-and-resumed run must
reproduce byte for byte.

The totals of ``reliability_support.COUNTS`` (kills survived, cases checked, ...) are printed at
the end of the pytest run so the CI log shows them (docs/reliability.md quotes one run).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from reliability_support import CAPTURE, CONVERT_KW, COUNTS


def pytest_terminal_summary(terminalreporter):
    if COUNTS:
        terminalreporter.write_sep("-", "reliability counts (this run)")
        for key in sorted(COUNTS):
            terminalreporter.write_line(f"{key}: {COUNTS[key]}")


@pytest.fixture(scope="session")
def rel_character(tmp_path_factory) -> Path:
    """The procedural character at a small face and texture budget."""
    from deliffas.geometry.procedural import ProceduralConfig, make_procedural_character

    return make_procedural_character(ProceduralConfig(tmp_path_factory.mktemp("rel_character"), seed=0,
                                                      target_faces=1500, texture_size=128))


@pytest.fixture(scope="session")
def rel_subject(tmp_path_factory, rel_character) -> Path:
    """The session capture (read-only)."""
    from deliffas.data.synth import SynthConfig, synthesize_capture

    out = tmp_path_factory.mktemp("rel_subject") / "subject"
    synthesize_capture(out, SynthConfig(**CAPTURE, character=str(rel_character)))
    return out


@pytest.fixture(scope="session")
def rel_reference(tmp_path_factory, rel_subject) -> Path:
    """The uninterrupted conversion of ``rel_subject`` (in-process, read-only)."""
    from deliffas.data.convert import ConvertConfig, convert

    out = tmp_path_factory.mktemp("rel_reference") / "out"
    convert(rel_subject, out, ConvertConfig(**CONVERT_KW, progress=False))
    return out
