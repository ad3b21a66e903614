"""DNA-Rendering .smc: camera-to-world metres + OpenCV pixel centres pinned against cv2.projectPoints; images, masks, SMPL-X; malformed files named."""

from __future__ import annotations

import cv2
import h5py
import numpy as np
import pytest

from capture_cameras import POINTS_MM, rig
from deliffas.io.infra.reader_checks import CaptureFormatError
from deliffas.io.formats.dna_rendering import SmcFile, SmcSmplx, cameras_to_smc, read_smc_calibration, smc_to_cameras, write_smc

K = np.array([[2400.0, 0, 1223.1], [0, 2398.0, 1025.6], [0, 0, 1]])
A = 2.1
RT = np.array([[np.cos(A), 0, np.sin(A), 2.4], [0, 1, 0, 1.3], [-np.sin(A), 0, np.cos(A), -1.7], [0, 0, 0, 1.0]])


def _smc(path, **over):
    """An .smc written by hand in the layout SMCReader reads (annotation-file groups)."""
    with h5py.File(path, "w") as h5:
        g = h5.create_group("Camera_Parameter/00")
        for key, val in {"K": K, "D": np.zeros(5), "RT": RT, "Color_Calibration": np.eye(3)}.items():
            val = over.get(key, val)
            if val is not None:
                g[key] = val
        ok, buf = cv2.imencode(".jpg", np.zeros((2048, 2448, 3), np.uint8))
        h5["Mask/0/mask/0"] = buf.ravel()
    return path


def test_projection_matches_opencv(tmp_path):
    (cam,) = smc_to_cameras(_smc(tmp_path / "a_annots.smc"))
    w2c = np.linalg.inv(RT)  # dataset_readers.py: c2w = RT, w2c = inv(c2w)
    rvec = cv2.Rodrigues(w2c[:3, :3])[0]
    theirs = cv2.projectPoints(POINTS_MM / 1000.0, rvec, w2c[:3, 3], K, np.zeros(5))[0].reshape(-1, 2)
    ours, _ = cam.project(POINTS_MM)
    assert np.abs((ours - 0.5) - theirs).max() < 1e-6
    assert (cam.width, cam.height) == (2448, 2048)  # from the mask (no colour images)


def test_images_masks_smplx(tmp_path):
    rng = np.random.default_rng(0)
    imgs = {"0": [np.full((24, 32, 3), (200, 30, 90), np.uint8), rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)],
            "1": [np.zeros((24, 32, 3), np.uint8)]}
    masks = {"0": [np.pad(np.full((8, 16), 255, np.uint8), 8)]}  # (24, 32)
    smplx = SmcSmplx(np.zeros((1, 10)), np.zeros((3, 10)), np.zeros((3, 55, 3)), np.ones((3, 3)), 1.0)
    write_smc(tmp_path / "m.smc", cameras_to_smc([c.rescaled(32, 24) for c in rig()[:2]]), imgs, masks, smplx, jpeg_quality=100)
    with SmcFile(tmp_path / "m.smc") as smc:
        assert smc.frame_count(0) == 2 and smc.frame_count(1) == 1 and smc.frame_count(0, kind="mask") == 1
        red = smc.image(0, 0)
        assert red.shape == (24, 32, 3) and np.abs(red.astype(int) - (200, 30, 90)).max() <= 3  # RGB, JPEG-close
        assert smc.mask(0, 0).shape == (24, 32) and smc.mask(0, 0)[12, 16] > 250 and smc.mask(0, 0)[0, 0] < 5
        assert smc.image_size(0) == (32, 24)
        s = smc.smplx()
        assert s.fullpose.shape == (3, 55, 3) and s.transl[1, 2] == 1
        with pytest.raises(CaptureFormatError, match=r"m\.smc: Camera_5mp/0/color/9: missing"):
            smc.image(0, 9)
    names = [c.name for c in smc_to_cameras(tmp_path / "m.smc")]
    assert names == ["cam0", "cam1"]  # the deliffas name rides in an attribute; ids are "00", "01"
    assert [c.camera_id for c in read_smc_calibration(tmp_path / "m.smc")] == ["00", "01"]


@pytest.mark.parametrize("over,pattern", [
    ({"RT": None}, r"x\.smc: Camera_Parameter/00/RT: missing"),
    ({"K": np.eye(4)}, r"x\.smc: Camera_Parameter/00/K: expected shape \(3, 3\), got \(4, 4\)"),
    ({"D": np.array([0.1, np.nan, 0, 0, 0])}, r"x\.smc: Camera_Parameter/00/D: expected finite numbers"),
    ({"RT": np.diag([1.0, 1.0, -1.0, 1.0])}, r"x\.smc: Camera_Parameter/00/RT: expected a rotation .*det R = -1"),
    ("truncated", r"x\.smc: HDF5: expected a complete HDF5 \(\.smc\) file"),
    ("missing", r"x\.smc: file: not found"),
])
def test_malformed(tmp_path, over, pattern):
    path = tmp_path / "x.smc"
    if over == "truncated":
        data = _smc(tmp_path / "full.smc").read_bytes()
        path.write_bytes(data[: len(data) // 3])
    elif over != "missing":
        _smc(path, **over)
    with pytest.raises(CaptureFormatError, match=pattern):
        read_smc_calibration(path)


def test_member_names_that_are_not_utf8(tmp_path):
    """h5py lists a member name that is not UTF-8 as bytes (found by the soak-scale fuzz: a damaged name in
    Camera_Parameter raised TypeError while sorting); it is a CaptureFormatError naming the group."""
    path = _smc(tmp_path / "x.smc")
    with h5py.File(path, "a") as h5:
        h5["Camera_Parameter"].create_group(b"\xff1")
        h5["Mask/0/mask"].create_group(b"\xfe2")
    with pytest.raises(CaptureFormatError, match=r"x\.smc: Camera_Parameter: member name b'\\xff1' is not UTF-8"):
        read_smc_calibration(path)
    with SmcFile(path) as smc, pytest.raises(CaptureFormatError, match=r"x\.smc: Mask/0/mask: member name"):
        smc.image_size(0)


def _heap_objects(data: bytes, collection: int) -> list[tuple[int, int, int]]:
    """(byte offset, index, size) of the objects of the global heap collection at ``collection``."""
    import struct

    size = struct.unpack_from("<Q", data, collection + 8)[0]
    p, out = collection + 16, []
    while p + 16 <= collection + size:
        index, obj_size = struct.unpack_from("<H", data, p)[0], struct.unpack_from("<Q", data, p + 8)[0]
        out.append((p, index, obj_size))
        if index == 0:
            break
        p += 16 + (obj_size + 7) // 8 * 8
    return out


def test_damaged_global_heap_is_refused_not_a_hang(tmp_path):
    """A variable-length attribute (a camera name) lives in a global heap; an object size damaged so that the
    next object header is zeros made libhdf5 2.0 loop forever reading the name (found by the soak). The file
    is refused before h5py reads it, naming the heap and the object."""
    from deliffas.io.infra.hdf5_heaps import looping_global_heap

    path = _smc(tmp_path / "x.smc")
    with h5py.File(path, "a") as h5:
        h5["Camera_Parameter/00"].attrs["name"] = "cam 00"  # a variable-length string: the global heap
    assert read_smc_calibration(path)[0].name == "cam 00"
    assert looping_global_heap(path) is None
    data = bytearray(path.read_bytes())
    collection = data.find(b"GCOL\x01\x00\x00\x00")
    offset, index, size = _heap_objects(bytes(data), collection)[0]
    assert index > 0 and size < 64
    data[offset + 8:offset + 16] = (1024).to_bytes(8, "little")  # the next header falls in the zeroed free space
    path.write_bytes(bytes(data))
    assert "does not advance" in looping_global_heap(path)
    with pytest.raises(CaptureFormatError, match=rf"x\.smc: HDF5 global heap: damaged: global heap collection at "
                                                 rf"byte {collection}: object 0 at byte \d+ records size 0"):
        SmcFile(path)
    data[offset + 8:offset + 16] = (1 << 40).to_bytes(8, "little")
    path.write_bytes(bytes(data))
    assert "runs past the collection" in looping_global_heap(path)
