"""Property-based fuzzing of every DynaCap reader: a correct parse or DynaCapFormatError, nothing else.

Each case starts from a small valid file and mutates it (truncation, shuffled lines, mistyped or
NaN tokens, huge counts, other encodings, CRLF/LF mixes, NUL bytes). The readers must end every
case with either a record or ``DynaCapFormatError`` naming the file and a line — never another
exception type, never a hang (pytest-timeout), never unbounded memory (counts are checked against
the lines that remain before anything is allocated).
"""

from __future__ import annotations

import itertools
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from deliffas.io.formats.dynacap import character as dc
from deliffas.io.formats.dynacap import skeleton as skeleton_io
from deliffas.io.formats.dynacap.calibration import read_calibration, write_calibration
from deliffas.io.formats.dynacap.meshes import MeshSequence, read_meshes, write_meshes
from deliffas.io.cameras import Camera
from deliffas.io.motion import Motion
from deliffas.io.formats.dynacap.character import DynaCapFormatError
from reliability_support import COUNTS, FUZZ_EXAMPLES

pytestmark = pytest.mark.timeout(300 if FUZZ_EXAMPLES <= 1000 else 3600)

CASES_RUN = itertools.count()


def _valid_files(d: Path) -> dict[str, tuple[Path, object]]:
    """Write one small valid file of every kind; return name -> (path, reader)."""
    joints = (
        skeleton_io.Joint("Root_tx", "prismatic", "none", np.array([0.0, 900, 0]), np.array([1.0, 0, 0])),
        skeleton_io.Joint("Root_ry", "revolute", "Root_tx", np.zeros(3), np.array([0.0, 1, 0])),
        skeleton_io.Joint("Spine_rx", "revolute", "Root_ry", np.array([0.0, 200, 0]), np.array([1.0, 0, 0])),
        skeleton_io.Joint("HeadEE", "revolute", "Spine_rx", np.array([0.0, 400, 0]), np.array([0.0, 0, 1])),
    )
    dofs = (skeleton_io.Dof("translate_x", None, (("Root_tx", 1000.0),)),
            skeleton_io.Dof("rotate_y", (-3.0, 3.0), (("Root_ry", 1.0),)),
            skeleton_io.Dof("spine_bend", None, (("Spine_rx", 0.5), ("HeadEE", 0.5))))
    markers = (skeleton_io.Marker("m1", "Spine_rx", "point", (1.0, 2.0, 3.0, 10.0, 1.0, 0.0, 0.0)),)
    skel = skeleton_io.Skeleton(joints, markers, (("grp", ("Spine_rx",)),), dofs)
    files = {}
    skeleton_io.write_skeleton(d / "a.skeleton", skel)
    files["skeleton"] = (d / "a.skeleton", skeleton_io.read_skeleton)
    motion = Motion(np.arange(4), np.random.default_rng(0).normal(size=(4, 3)))
    dc.write_motion(d / "a.motion", motion)
    files["motion"] = (d / "a.motion", lambda p: dc.read_motion(p, 3))
    skin = dc.Skin(("Root", "Spine", "Head"), np.array([[0, 1], [1, 2], [2, -1], [0, -1]]),
                   np.array([[0.7, 0.3], [0.6, 0.4], [1.0, 0], [1.0, 0]]))
    dc.write_skin(d / "a.skin", skin)
    files["skin"] = (d / "a.skin", lambda p: dc.read_skin(p, 4))
    obj = dc.ObjData(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]),
                     np.array([[0, 1, 2], [0, 1, 3], [1, 2, 3], [0, 2, 3]]),
                     np.array([[0.0, 0], [1, 0], [0, 1], [1, 1]]), np.array([[0, 1, 2], [0, 1, 3], [1, 2, 3], [0, 2, 3]]))
    dc.write_obj(d / "a.obj", obj)
    files["obj"] = (d / "a.obj", dc.read_obj)
    dc.write_segmentation(d / "segmentation.txt", np.array([0, 5, 12, 18]))
    files["segmentation"] = (d / "segmentation.txt", lambda p: dc.read_segmentation(p, 4))
    write_meshes(d / "a.meshes", MeshSequence(np.arange(3), np.ones((3, 4, 3), np.float32)))
    files["meshes"] = (d / "a.meshes", lambda p: read_meshes(p, 4))
    cam = Camera("0", np.array([[500.0, 0, 32], [0, 500, 32], [0, 0, 1]]), np.eye(4), 64, 64)
    write_calibration(d / "a.calibration", [cam, Camera("1", cam.K, cam.world_to_cam, 64, 64)])
    files["calibration"] = (d / "a.calibration", read_calibration)
    (d / "a.character").write_text("skeletool character file v1.0\nskeleton\n  a.skeleton\nmesh\n  a.obj\nskin\n  a.skin\npose\n  a.motion\n")
    files["character"] = (d / "a.character", dc.read_character)
    return files


_TEMPLATE_DIR = Path(tempfile.mkdtemp(prefix="deliffas-fuzz-"))
VALID = _valid_files(_TEMPLATE_DIR)


def test_valid_files_parse():
    for name, (path, reader) in VALID.items():
        assert reader(path) is not None, name


# ---------------------------------------------------------------------------------- mutations
NASTY_TOKENS = ["nan", "NaN", "inf", "-inf", "1e999", "", "x", "0x1F", "1" * 5000, "-1", "99999999999",
                "1.5.5", "１２", "\t", "\x00", "é", "none", "revolute", "joints:", "1e-999", "-0"]


@st.composite
def mutated(draw, name: str):
    data = VALID[name][0].read_bytes()
    lines = data.split(b"\n")
    kind = draw(st.sampled_from(["truncate", "shuffle", "token", "drop_line", "dup_line", "huge_count",
                                 "encoding", "newlines", "nul", "bytes", "swap_tokens"]))
    if kind == "truncate":
        data = data[: draw(st.integers(0, len(data)))]
    elif kind == "shuffle":
        perm = draw(st.permutations(range(len(lines))))
        data = b"\n".join(lines[i] for i in perm)
    elif kind in ("token", "swap_tokens", "huge_count"):
        i = draw(st.integers(0, len(lines) - 1))
        toks = lines[i].split(b" ")
        j = draw(st.integers(0, max(len(toks) - 1, 0)))
        if kind == "token":
            toks[j] = draw(st.sampled_from(NASTY_TOKENS)).encode("utf-8", "surrogatepass")
        elif kind == "huge_count":
            toks[j] = str(draw(st.sampled_from([10**6, 10**9, 2**63, -5]))).encode()
        else:
            k = draw(st.integers(0, max(len(toks) - 1, 0)))
            toks[j], toks[k] = toks[k], toks[j]
        lines[i] = b" ".join(toks)
        data = b"\n".join(lines)
    elif kind == "drop_line":
        i = draw(st.integers(0, len(lines) - 1))
        data = b"\n".join(lines[:i] + lines[i + 1:])
    elif kind == "dup_line":
        i = draw(st.integers(0, len(lines) - 1))
        data = b"\n".join(lines[:i] + [lines[i]] * draw(st.integers(2, 50)) + lines[i:])
    elif kind == "encoding":
        enc = draw(st.sampled_from(["utf-16", "utf-32", "latin-1", "cp1252"]))
        data = data.decode("utf-8").replace("Root", "Rööt").encode(enc)
    elif kind == "newlines":
        seps = draw(st.lists(st.sampled_from([b"\n", b"\r\n", b"\r", b"\n\n", b" \t\n"]), min_size=len(lines), max_size=len(lines)))
        data = b"".join(ln + s for ln, s in zip(lines, seps))
    elif kind == "nul":
        pos = draw(st.integers(0, len(data)))
        data = data[:pos] + b"\x00" + data[pos:]
    else:
        pos = draw(st.integers(0, max(len(data) - 1, 0)))
        data = data[:pos] + draw(st.binary(min_size=1, max_size=8)) + data[pos + 1:]
    return data


def _check(name: str, data: bytes, tmp: Path) -> None:
    src, reader = VALID[name]
    target = tmp / src.name
    if name == "character":
        for other in ("a.skeleton", "a.obj", "a.skin", "a.motion"):
            if not (tmp / other).exists():
                (tmp / other).write_bytes((src.parent / other).read_bytes())
    target.write_bytes(data)
    next(CASES_RUN)
    try:
        reader(target)
    except DynaCapFormatError as err:
        assert str(target.name) in str(err) or err.path.endswith((".skeleton", ".obj", ".skin", ".motion"))
        assert err.line >= 0
        assert isinstance(err, ValueError)


SETTINGS = settings(max_examples=FUZZ_EXAMPLES, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.mark.parametrize("name", sorted(VALID))
def test_reader_fuzz(name, tmp_path):
    @SETTINGS
    @given(data=mutated(name))
    def run(data):
        _check(name, data, tmp_path)

    run()


@SETTINGS
@given(text=st.text(max_size=400))
def test_arbitrary_text_never_crashes(text):
    d = Path(tempfile.mkdtemp(prefix="deliffas-fuzz-text-"))
    for name, (src, reader) in VALID.items():
        if name == "character":
            continue
        p = d / src.name
        p.write_text(text, encoding="utf-8", errors="surrogatepass") if False else p.write_bytes(text.encode("utf-8", "replace"))
        try:
            reader(p)
        except DynaCapFormatError:
            pass


def test_report_fuzz_count(capsys):
    """Prints the number of fuzzed cases of this run (for the reliability note)."""
    n = next(CASES_RUN)
    COUNTS["fuzz: DynaCap/OBJ reader cases"] += n
    with capsys.disabled():
        print(f"\n[fuzz] {n} mutated reader cases ended in a parse or DynaCapFormatError")
    assert n > 0
