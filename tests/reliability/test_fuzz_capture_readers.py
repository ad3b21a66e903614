"""Property-based fuzzing of the capture-format readers: valid data or a ValueError naming the file, nothing else.

Every format ``read_cameras`` reads (EasyMocap, ZJU-MoCap, nerfstudio, THuman4.0, ActorsHQ, COLMAP text
and binary, DNA-Rendering .smc, Pose2Sim Calib.toml, Qualisys .qca.txt, CMU Panoptic; DynaCap's .calibration
is fuzzed in ``test_fuzz_readers.py``), the
SMPL records of the capture formats, the frame sources of ``capture_frames``, AMASS motions and SMPL
model files (.npz, .pkl). Each case starts from a small valid file written by deliffas' own writers
(``capture_seeds``) and damages one of its files (``fuzz_mutations``: bytes, text lines and tokens,
or one structural edit of the parsed JSON/YAML/npz/npy/pickle/HDF5 tree). The reader must return data
that is valid (finite, the documented shapes, rotations orthonormal with det +1) or raise a
ValueError (``CaptureFormatError``, ``SMPLMotionError``, ``SMPLModelError``) whose message names the
file — never KeyError, IndexError, TypeError, AttributeError, cv2.error, h5py's or zipfile's errors.
``make soak`` runs 10,000 cases per reader (``reliability_support.FUZZ_EXAMPLES``).
"""

from __future__ import annotations

import json
import pickle
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from reliability_support import COUNTS, FUZZ_EXAMPLES

import capture_seeds as cs
from deliffas.io.body_models.amass import read_smpl_motion
from deliffas.io.camera_conventions import DISTORTION
from deliffas.io.camera_formats import read_cameras
from deliffas.io.infra.reader_checks import CaptureFormatError
from deliffas.io.formats.capture_frames import FileFramesSpec, SmcFramesSpec, Undistortion
from deliffas.io.cameras import ROTATION_TOLERANCE, Camera
from deliffas.io.formats.dna_rendering import SmcFile
from deliffas.io.formats.easymocap import read_easymocap_smpl
from deliffas.io.body_models.smpl import NUM_JOINTS, NUM_POSE_BASIS, load_smpl_model
from deliffas.io.formats.thuman4 import read_thuman4_smplx
from deliffas.io.formats.zju_mocap import read_zju_params
from fuzz_mutations import bytes_cases, text_cases, tree_cases

pytestmark = pytest.mark.timeout(300 if FUZZ_EXAMPLES <= 1000 else 3600)

SETTINGS = settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                           HealthCheck.data_too_large])

SEEDS = Path(tempfile.mkdtemp(prefix="deliffas-fuzz-capture-"))
cs.write_seeds(SEEDS)
SIZE = (cs.W, cs.H)


# ------------------------------------------------------------------------------------ valid output
def _finite(a: Any, shape: tuple[int | None, ...]) -> np.ndarray:
    a = np.asarray(a)
    assert a.dtype.kind == "f" and len(a.shape) == len(shape), (a.dtype, a.shape, shape)
    assert all(s is None or s == n for s, n in zip(shape, a.shape)), (a.shape, shape)
    assert np.isfinite(a).all()
    return a


def check_cameras(cams: list) -> None:
    assert isinstance(cams, list) and cams
    assert len({c.name for c in cams}) == len(cams), [c.name for c in cams]  # unique names
    for c in cams:
        assert isinstance(c, Camera) and isinstance(c.name, str)
        K = _finite(c.K, (3, 3))
        assert abs(np.linalg.det(K)) > 0
        assert np.array_equal(K[2], [0, 0, 1]) and K[0, 0] > 0 and K[1, 1] > 0  # plausible (check_camera)
        assert -c.width <= K[0, 2] <= 2 * c.width and -c.height <= K[1, 2] <= 2 * c.height
        E = _finite(c.world_to_cam, (4, 4))
        assert np.array_equal(E[3], [0, 0, 0, 1])
        R = E[:3, :3]
        assert np.abs(R @ R.T - np.eye(3)).max() <= ROTATION_TOLERANCE and abs(np.linalg.det(R) - 1) <= ROTATION_TOLERANCE
        assert isinstance(c.width, int) and isinstance(c.height, int) and c.width > 0 and c.height > 0
        if DISTORTION in c.extra:
            _finite(c.extra[DISTORTION], (5,))


def check_people(people: list) -> None:
    assert isinstance(people, list)
    for s in people:
        check_person(s)


def check_person(s) -> None:
    assert isinstance(s.id, int)
    _finite(s.Rh, (1, 3)), _finite(s.Th, (1, 3)), _finite(s.poses, (1, None)), _finite(s.shapes, (1, None))
    if s.expression is not None:
        _finite(s.expression, (1, None))


def check_thuman4_smplx(s) -> None:
    n = s.num_frames
    assert n >= 1
    _finite(s.global_orient, (n, 3)), _finite(s.transl, (n, 3)), _finite(s.body_pose, (n, 63))
    _finite(s.betas, (None, None))
    for a in s.others.values():
        assert np.asarray(a).shape[0] == n
        assert np.isfinite(a).all()


def check_smc_smplx(s) -> None:
    n = s.fullpose.shape[0]
    assert n >= 1
    _finite(s.fullpose, (n, 55, 3)), _finite(s.transl, (n, 3)), _finite(s.expression, (n, None))
    _finite(s.betas, (None, None))
    assert np.isfinite(s.scale)


def check_frames(frames: list) -> None:
    for rgb, mask in frames:
        assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3
        assert mask.dtype == np.uint8 and mask.shape == rgb.shape[:2]


def check_motion(m) -> None:
    n = m.num_frames
    assert n >= 1
    poses = _finite(m.poses, (n, None))
    assert poses.shape[1] >= 72 and poses.shape[1] % 3 == 0
    _finite(m.trans, (n, 3))
    assert _finite(m.betas, (None,)).shape[0] >= 10
    assert m.fps is None or (np.isfinite(m.fps) and m.fps > 0)
    assert m.frames is None or (m.frames.shape == (n,) and np.all(np.diff(m.frames) > 0))
    assert m.smpl_pose.shape == (n, 72)


def check_smpl_model(m) -> None:
    V = m.num_verts
    assert V >= 1
    _finite(m.v_template, (V, 3)), _finite(m.shapedirs, (V, 3, None)), _finite(m.posedirs, (V, 3, NUM_POSE_BASIS))
    _finite(m.J_regressor, (NUM_JOINTS, V)), _finite(m.weights, (V, NUM_JOINTS))
    assert m.faces.ndim == 2 and m.faces.shape[1] == 3 and (m.faces.size == 0 or (m.faces.min() >= 0 and m.faces.max() < V))
    assert m.parents[0] == -1 and all(0 <= m.parents[j] < j for j in range(1, NUM_JOINTS))


# ----------------------------------------------------------------------------------------- readers
def _read_smc_frames(d: Path) -> list:
    spec = SmcFramesSpec(d / "a.smc", ("0", "1"), (0, 1),
                         undistort={1: Undistortion(np.array([[30.0, 0, 15.5], [0, 30, 11.5], [0, 0, 1]]), cs.FULL)})
    src = spec.open()
    try:
        return [src.read(f, c) for f in (0, 1) for c in (0, 1)]
    finally:
        src.close()


def _read_smc_smplx(d: Path):
    with SmcFile(d / "a.smc") as smc:
        return smc.smplx()


def _read_frame_files(d: Path) -> list:
    row = tuple(f"images/cam{i}/000000.jpg" for i in range(2))
    masks = tuple(f"masks/cam{i}/000000.png" for i in range(2))
    spec = FileFramesSpec(d, {0: row}, {0: masks},
                          undistort={1: Undistortion(np.array([[30.0, 0, 15.5], [0, 30, 11.5], [0, 0, 1]]), cs.FULL)})
    src = spec.open()
    return [src.read(0, c) for c in range(2)]


@dataclass(frozen=True)
class FileKind:
    """How the cases of one file are made: byte damage always, text damage with ``text_sep``, and one
    structural edit when the file has a parse tree (``tree_of`` reads it, ``to_bytes`` writes it back)."""

    text_sep: bytes | None = None
    tree_of: Callable[[Path], Any] | None = None
    to_bytes: Callable[[Any], bytes] | None = None
    values: str = "json"

    def cases(self, path: Path):
        valid = path.read_bytes()
        out = [bytes_cases(valid)]
        if self.text_sep is not None:
            out.append(text_cases(valid, self.text_sep))
        if self.tree_of is not None:
            out.append(tree_cases(self.tree_of(path), self.values).map(self.to_bytes))
        return st.one_of(*out)


@dataclass(frozen=True)
class Target:
    """One capture reader under fuzz.

    Attributes:
        seed: the folder of valid files under ``SEEDS`` (copied once per test; each case replaces one file).
        files: relative path -> how its cases are made.
        readers: (name, read(case folder), check(result)) run on every case; each must end in data that
            passes ``check`` or in a ValueError naming a file of the case folder.
    """

    seed: str
    files: dict[str, FileKind]
    readers: tuple[tuple[str, Callable[[Path], Any], Callable[[Any], None]], ...]


BINARY = FileKind()
_JSON = FileKind(b",", lambda p: json.loads(p.read_text()), cs.json_bytes)
_NPZ = FileKind(None, cs.npz_tree, cs.npz_bytes, "numpy")
_NPY = FileKind(None, cs.npy_dict_tree, cs.npy_dict_bytes, "numpy")
_H5 = FileKind(None, cs.h5_tree, cs.h5_bytes, "numpy")
_PKL = FileKind(None, lambda p: pickle.loads(p.read_bytes()), cs.pickle_bytes, "numpy")
_YAML = FileKind(b" ", cs.easymocap_tree, cs.easymocap_bytes)

TARGETS = {
    "easymocap cameras": Target("easymocap", {"intri.yml": _YAML, "extri.yml": _YAML}, (
        ("read_cameras easymocap", lambda d: read_cameras(d, "easymocap", size=SIZE), check_cameras),)),
    "easymocap smpl": Target("easymocap", {"smpl/000000.json": _JSON}, (
        ("read_easymocap_smpl", lambda d: read_easymocap_smpl(d / "smpl/000000.json"), check_people),)),
    "zju annots": Target("zju", {"annots.npy": _NPY}, (
        ("read_cameras zju", lambda d: read_cameras(d / "annots.npy", "zju", size=SIZE), check_cameras),)),
    "zju params": Target("zju", {"params/0.npy": _NPY}, (
        ("read_zju_params", lambda d: read_zju_params(d / "params/0.npy"), check_person),)),
    "nerfstudio": Target("nerfstudio", {"transforms.json": _JSON}, (
        ("read_cameras nerfstudio", lambda d: read_cameras(d, "nerfstudio"), check_cameras),)),
    "thuman4 calibration": Target("thuman4", {"calibration.json": _JSON}, (
        ("read_cameras thuman4", lambda d: read_cameras(d, "thuman4"), check_cameras),)),
    "thuman4 smplx": Target("thuman4", {"smpl_params.npz": _NPZ}, (
        ("read_thuman4_smplx", lambda d: read_thuman4_smplx(d / "smpl_params.npz"), check_thuman4_smplx),)),
    "actorshq": Target("actorshq", {"calibration.csv": FileKind(b",")}, (
        ("read_cameras actorshq", lambda d: read_cameras(d, "actorshq"), check_cameras),)),
    "pose2sim calib.toml": Target("pose2sim", {"Calib.toml": FileKind(b" ")}, (
        ("read_cameras pose2sim", lambda d: read_cameras(d, "pose2sim"), check_cameras),)),
    "qualisys qca": Target("qualisys", {"Calib.qca.txt": FileKind(b" ")}, (
        ("read_cameras qualisys", lambda d: read_cameras(d / "Calib.qca.txt", "qualisys"), check_cameras),)),
    "panoptic calibration": Target("panoptic", {"calibration_panoptic.json": _JSON}, (
        ("read_cameras panoptic", lambda d: read_cameras(d, "panoptic"), check_cameras),)),
    "colmap text": Target("colmap_text", {"cameras.txt": FileKind(b" "), "images.txt": FileKind(b" ")}, (
        ("read_cameras colmap", lambda d: read_cameras(d, "colmap"), check_cameras),)),
    "colmap binary": Target("colmap_binary", {"cameras.bin": BINARY, "images.bin": BINARY}, (
        ("read_cameras colmap", lambda d: read_cameras(d, "colmap"), check_cameras),)),
    "dna smc": Target("dna", {"a.smc": _H5}, (
        ("read_cameras dna", lambda d: read_cameras(d / "a.smc", "dna", size=SIZE), check_cameras),
        ("SmcFile.smplx", _read_smc_smplx, check_smc_smplx),
        ("SmcFrameSource.read", _read_smc_frames, check_frames))),
    "frame files": Target("frames", {f"{k}/cam{i}/000000.{ext}": BINARY for k, ext in (("images", "jpg"), ("masks", "png"))
                                     for i in range(2)}, (
        ("FileFrameSource.read", _read_frame_files, check_frames),)),
    "amass motion": Target("amass", {"motion.npz": _NPZ}, (
        ("read_smpl_motion", lambda d: read_smpl_motion(d / "motion.npz"), check_motion),)),
    "smpl model npz": Target("smpl", {"model.npz": _NPZ}, (
        ("load_smpl_model npz", lambda d: load_smpl_model(d / "model.npz"), check_smpl_model),)),
    "smpl model pkl": Target("smpl", {"model.pkl": _PKL}, (
        ("load_smpl_model pkl", lambda d: load_smpl_model(d / "model.pkl"), check_smpl_model),)),
}


def _run_readers(target: Target, case: Path) -> None:
    for name, read, check in target.readers:
        try:
            result = read(case)
        except ValueError as err:  # the readers' own errors are ValueErrors naming the file
            assert str(case) in str(err), f"{name}: the error does not name the file: {err}"
            if isinstance(err, CaptureFormatError):
                assert err.key, f"{name}: no key in {err}"
        else:
            check(result)


def _strategy(target: Target, folder: Path):
    return st.one_of(*[st.tuples(st.just(rel), kind.cases(folder / rel)) for rel, kind in target.files.items()])


@pytest.mark.parametrize("name", list(TARGETS))
def test_seed_is_valid(name, tmp_path):
    """The unmutated seed reads, and so does its parse tree written back (the serialisers are faithful)."""
    target = TARGETS[name]
    case = tmp_path / "case"
    shutil.copytree(SEEDS / target.seed, case)
    for _, read, check in target.readers:
        check(read(case))
    for rel, kind in target.files.items():
        if kind.tree_of is not None:
            (case / rel).write_bytes(kind.to_bytes(kind.tree_of(case / rel)))
    for _, read, check in target.readers:
        check(read(case))


@pytest.mark.parametrize("name", list(TARGETS))
def test_capture_reader_fuzz(name, tmp_path):
    target = TARGETS[name]
    case = tmp_path / "case"
    shutil.copytree(SEEDS / target.seed, case)
    originals = {rel: (case / rel).read_bytes() for rel in target.files}
    cases = 0

    @SETTINGS
    @given(change=_strategy(target, case))
    def run(change):
        nonlocal cases
        rel, data = change
        cases += 1
        (case / rel).write_bytes(data)
        try:
            _run_readers(target, case)
        finally:
            (case / rel).write_bytes(originals[rel])

    run()
    COUNTS[f"fuzz: {name} cases"] += cases
