"""Small valid files of every capture format, written by deliffas' own writers, and the serialisers that turn
a mutated parse tree back into a file: the seeds of ``test_fuzz_capture_readers.py``.

``write_seeds(root)`` writes one folder per format under ``root`` (3 cameras at 64 x 48 with OpenCV
distortion where the format holds it, SMPL records, a 2-camera .smc with JPEG frames and masks, image and
mask files, an AMASS motion, SMPL model files as .npz and .pkl). ``*_tree`` read a seed into plain
dicts/lists/arrays for ``fuzz_mutations.tree_cases``; ``*_bytes`` write such a tree back in the format.
"""

from __future__ import annotations

import io
import json
import pickle
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from deliffas.io.camera_conventions import DISTORTION
from deliffas.io.camera_formats import write_cameras
from deliffas.io.cameras import Camera, look_at

W, H = 64, 48
"""Image size of the seed cameras (stored by the formats that store one; passed as size= to the others)."""
FULL = np.array([-0.21, 0.043, 1.1e-3, -7e-4, -0.005])
RADIAL = np.array([-0.12, 0.021, 0.0, 0.0, 0.0013])


def rig(distortion: np.ndarray | None) -> list[Camera]:
    """Three cameras 3 m around the origin, non-square pixels, off-centre principal points."""
    cams = []
    for i in range(3):
        a = 2 * np.pi * i / 3 + 0.3
        E = look_at(np.array([3000 * np.cos(a), 900 + 200 * i, 3000 * np.sin(a)]), np.array([10.0 * i, 950.0, -20.0]))
        K = np.array([[150.0 + 17.3 * i, 0.0, 30.5 + i], [0.0, 152.0 + 3 * i, 22.5 - i], [0.0, 0.0, 1.0]])
        extra = {} if distortion is None else {DISTORTION: distortion * (1 + 0.1 * i)}
        cams.append(Camera(f"cam{i}", K, E, W, H, extra=extra))
    return cams


def _image(seed: int, shape: tuple[int, ...]) -> np.ndarray:
    """A smooth (H, W) or (H, W, 3) uint8 test image (JPEG-friendly, so the seed files stay small)."""
    y, x = np.mgrid[: shape[0], : shape[1]]
    g = ((x * (3 + seed) + y * (5 - seed)) % 256).astype(np.uint8)
    return g if len(shape) == 2 else np.stack([g, 255 - g, g // 2], -1)


def _smpl_model_arrays() -> dict:
    """An SMPL-layout model of 12 vertices (an octahedron-ish ball): SMPL's tree, random small blend shapes."""
    from deliffas.io.body_models.smpl import SMPLModelData

    parents = np.array([-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21])
    rng = np.random.default_rng(0)
    V = 12
    J = rng.random((24, V))
    Wt = rng.random((V, 24)) ** 4
    faces = np.array([[i, (i + 1) % V, (i + 5) % V] for i in range(V)])
    return SMPLModelData(rng.normal(0, 0.3, (V, 3)), rng.normal(0, 0.01, (V, 3, 10)), rng.normal(0, 0.002, (V, 3, 207)),
                         J / J.sum(1, keepdims=True), Wt / Wt.sum(1, keepdims=True), parents, faces)


def write_seeds(root: Path) -> None:
    """Write the seed files of every format under ``root`` (see the module docstring)."""
    from deliffas.io.formats.actorshq import write_actorshq_calibration, camera_to_actorshq
    from deliffas.io.body_models.amass import SMPLMotion, write_smpl_motion
    from deliffas.io.formats.capture_frames import write_image_file
    from deliffas.io.formats.dna_rendering import SmcSmplx, cameras_to_smc, write_smc
    from deliffas.io.formats.easymocap import EasyMocapSmpl, write_easymocap_smpl
    from deliffas.io.body_models.smpl import write_smpl_model
    from deliffas.io.formats.thuman4 import Thuman4Smplx, camera_to_thuman4, write_thuman4_calibration, write_thuman4_smplx
    from deliffas.io.formats.zju_mocap import cameras_to_zju, write_zju_annots, write_zju_params

    full, none = rig(FULL), rig(None)
    rng = np.random.default_rng(1)
    person = EasyMocapSmpl(0, rng.normal(0, 0.3, (1, 3)), rng.normal(0, 1, (1, 3)), rng.normal(0, 0.2, (1, 72)),
                           rng.normal(0, 1, (1, 10)))
    write_cameras(full, root / "easymocap", "easymocap")
    write_easymocap_smpl(root / "easymocap" / "smpl" / "000000.json",
                         [person, replace(person, id=3, expression=rng.normal(0, 1, (1, 10)))])
    ims = [[f"images/{c.name}/{f:06d}.jpg" for c in full] for f in range(2)]
    write_zju_annots(root / "zju", cameras_to_zju(full, ims))
    write_zju_params(root / "zju" / "params" / "0.npy", person)
    path = write_cameras(full, root / "nerfstudio", "nerfstudio")
    meta = json.loads(path.read_text())
    meta.update({k: meta["frames"][0][k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1")})  # top-level fallbacks
    path.write_text(json.dumps(meta))
    th = [camera_to_thuman4(c, drop_distortion=True) for c in full]
    write_thuman4_calibration(root / "thuman4", [replace(th[0], distortion=FULL)] + th[1:])
    write_thuman4_smplx(root / "thuman4" / "smpl_params.npz", Thuman4Smplx(
        rng.normal(0, 1, (1, 10)), rng.normal(0, 0.3, (2, 3)), rng.normal(0, 1, (2, 3)), rng.normal(0, 0.2, (2, 63)),
        {"jaw_pose": np.zeros((2, 3)), "expression": rng.normal(0, 1, (2, 10)), "left_hand_pose": np.zeros((2, 45))}))
    write_actorshq_calibration(root / "actorshq", [camera_to_actorshq(c) for c in rig(RADIAL)])
    for fmt in ("pose2sim", "qualisys", "panoptic"):  # the camera formats registered as plug-in modules
        (root / fmt).mkdir()
        write_cameras(full, root / fmt, fmt)
    write_cameras(none, root / "colmap_text", "colmap", text=True)
    write_cameras(none, root / "colmap_binary", "colmap")
    frames = {str(i): [_image(i + f, (24, 32, 3)) for f in range(2)] for i in range(2)}
    masks = {str(i): [_image(i, (24, 32)) for _ in range(2)] for i in range(2)}
    write_smc(root / "dna" / "a.smc", cameras_to_smc(full), frames, masks,
              SmcSmplx(rng.normal(0, 1, (1, 10)), rng.normal(0, 1, (2, 10)), rng.normal(0, 0.2, (2, 55, 3)),
                       rng.normal(0, 1, (2, 3)), 1.0))
    for i in range(2):
        write_image_file(root / "frames" / "images" / f"cam{i}" / "000000.jpg", _image(i, (24, 32, 3)))
        write_image_file(root / "frames" / "masks" / f"cam{i}" / "000000.png", (_image(i, (24, 32)) > 128) * np.uint8(255))
    (root / "amass").mkdir()
    (root / "smpl").mkdir()
    write_smpl_motion(root / "amass" / "motion.npz", SMPLMotion(
        rng.normal(0, 0.2, (3, 156)), rng.normal(0, 1, (3, 3)), rng.normal(0, 1, 16), 30.0, "female", np.array([0, 2, 5])))
    model = _smpl_model_arrays()
    write_smpl_model(root / "smpl" / "model.npz", model)
    import scipy.sparse as sp

    with np.load(root / "smpl" / "model.npz") as z:
        raw = {k: z[k] for k in z.files}
    raw["J_regressor"] = sp.csc_matrix(raw["J_regressor"])  # as the official pickles store it
    (root / "smpl" / "model.pkl").write_bytes(pickle.dumps(raw, protocol=2))


# ------------------------------------------------------------------------------- trees and serialisers
def json_bytes(tree: Any) -> bytes:
    """JSON text of ``tree`` (NaN and Infinity written as Python's json does)."""
    return json.dumps(tree, allow_nan=True).encode()


def _as_array(v: Any) -> np.ndarray:
    try:
        return np.asanyarray(v)
    except ValueError:  # a ragged list: an object array, as np.save would pickle it
        out = np.empty(len(v), object)
        for i, x in enumerate(v):
            out[i] = x
        return out


def npz_tree(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def npz_bytes(tree: Any) -> bytes:
    """An ``.npz`` of ``tree``'s entries (object entries pickled, as ``np.savez`` does); a non-dict tree
    becomes a bare ``.npy``."""
    buf = io.BytesIO()
    if isinstance(tree, dict):
        np.savez(buf, **{str(k): _as_array(v) for k, v in tree.items()})
    else:
        np.save(buf, _as_array(tree))
    return buf.getvalue()


def npy_dict_tree(path: Path) -> dict:
    return np.load(path, allow_pickle=True).item()  # our own seed file


def npy_dict_bytes(tree: Any) -> bytes:
    """``np.save`` of ``tree`` as a 0-d object array (how ZJU-MoCap's dict files are made)."""
    a = np.empty((), object)
    a[()] = tree
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def pickle_bytes(tree: Any) -> bytes:
    return pickle.dumps(tree, protocol=2)


def h5_tree(path: Path) -> dict:
    """Groups as dicts, datasets as arrays, attributes as ``@name`` entries."""
    import h5py

    def walk(g) -> dict:
        out = {f"@{k}": v for k, v in g.attrs.items()}
        for k, v in g.items():
            out[k] = walk(v) if isinstance(v, h5py.Group) else v[()]
        return out

    with h5py.File(path, "r") as h5:
        return walk(h5)


def _h5_value(v: Any):
    import h5py

    if v is None:
        return h5py.Empty("f8")
    if isinstance(v, (set, tuple, list, dict)) or (isinstance(v, np.ndarray) and v.dtype == object):
        try:
            a = np.asarray(list(v) if isinstance(v, (set, tuple)) else v)
            if a.dtype.kind in "fiubc":
                return a
        except (ValueError, TypeError):
            pass
        return np.bytes_(repr(v)[:200])
    if isinstance(v, np.ndarray) and v.dtype.kind == "U":
        return v.astype("S")
    return v


def h5_bytes(tree: Any) -> bytes:
    """An HDF5 file of ``tree`` (the inverse of ``h5_tree``; what HDF5 cannot store becomes bytes)."""
    import h5py

    def fill(g, t: dict) -> None:
        for k, v in t.items():
            k = str(k).replace("/", "_").replace(".", "_") or "_"
            if k.startswith("@"):
                g.attrs[k[1:] or "_"] = _h5_value(v) if not isinstance(v, dict) else np.bytes_(repr(v)[:200])
            elif isinstance(v, dict):
                fill(g.create_group(k), v)
            else:
                g[k] = _h5_value(v)

    buf = io.BytesIO()
    with h5py.File(buf, "w") as h5:
        fill(h5, tree if isinstance(tree, dict) else {"value": tree})
    return buf.getvalue()


def easymocap_tree(path: Path) -> dict:
    """An EasyMocap ``intri.yml``/``extri.yml`` as {names: [...], key: matrix {rows, cols, dt, data} or number}."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    root = fs.root()
    out: dict = {}
    for key in root.keys():
        node = fs.getNode(key)
        if key == "names":
            out[key] = [node.at(i).string() for i in range(node.size())]
        elif node.isMap():
            m = node.mat()
            out[key] = {"rows": m.shape[0], "cols": m.shape[1] if m.ndim > 1 else 1, "dt": "d",
                        "data": [float(x) for x in m.ravel()]}
        else:
            out[key] = node.real()
    fs.release()
    return out


def _yaml_flow(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return ".nan" if v != v else (".Inf" if v == np.inf else ("-.Inf" if v == -np.inf else repr(v)))
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if v is None:
        return '""'
    if isinstance(v, list):
        return "[" + ", ".join(_yaml_flow(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))}: {_yaml_flow(x)}" for k, x in v.items()) + "}"
    return json.dumps(str(v))


def easymocap_bytes(tree: Any) -> bytes:
    """OpenCV FileStorage YAML of a tree from ``easymocap_tree`` (dict values written as !!opencv-matrix)."""
    if not isinstance(tree, dict):
        return ("%YAML:1.0\n---\nvalue: " + _yaml_flow(tree) + "\n").encode()
    text = "%YAML:1.0\n---\n"
    for key, v in tree.items():
        key = str(key) or "_"
        if isinstance(v, dict):
            text += f"{key}: !!opencv-matrix\n" + "".join(f"  {k or '_'}: {_yaml_flow(x)}\n" for k, x in v.items())
        elif isinstance(v, list):
            text += f"{key}:\n" + "".join(f"  - {_yaml_flow(x)}\n" for x in v) if v else f"{key}: []\n"
        else:
            text += f"{key}: {_yaml_flow(v)}\n"
    return text.encode()
