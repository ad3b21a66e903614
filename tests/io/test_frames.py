"""Frame sources: image folders, FFV1 videos (lossless, sequential + random access), mask folders."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from deliffas.io.formats.dynacap.frames import (
    FrameSource,
    ImageFolderSource,
    MaskFolderSource,
    VideoSource,
    VideoWriterSet,
    image_path,
    write_image,
)


def _frames(n, h=24, w=32, seed=0):
    rng = np.random.default_rng(seed)
    return [(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), rng.integers(0, 256, (h, w), dtype=np.uint8))
            for _ in range(n)]


def test_image_folder_round_trip(tmp_path):
    root = tmp_path / "seq" / "rgb_32_24"
    data = _frames(3)
    for f, (rgb, mask) in enumerate(data):
        write_image(root, f + 5, 2, rgb, mask)
    assert image_path(root, 5, 2).name == "image_alp_c_002_f_000005.png"
    assert image_path(root, 5, 2).parent.name == "000005"
    src = ImageFolderSource(tmp_path / "seq")
    assert isinstance(src, FrameSource) and src.frames() == [5, 6, 7]
    for f, (rgb, mask) in enumerate(data):
        r, m = src.read(f + 5, 2)
        assert np.array_equal(r, rgb) and np.array_equal(m, mask)
    with pytest.raises(FileNotFoundError, match="frame 9"):
        src.read(9, 2)


def test_video_round_trip_is_lossless_in_any_order(tmp_path):
    data = {c: _frames(12, seed=c) for c in range(2)}
    w = VideoWriterSet(tmp_path / "training", ["0", "1"], 32, 24, fps=25)
    for f in range(12):
        for c in range(2):
            w.write(c, *data[c][f])
    w.close()
    src = VideoSource(tmp_path / "training", ["0", "1"], first_frame=100, max_open=2)
    order = [100, 101, 102, 111, 103, 103, 110, 100, 105]  # forward, jump ahead, back, repeat
    for f in order:
        for c in (1, 0):
            rgb, mask = src.read(f, c)
            assert np.array_equal(rgb, data[c][f - 100][0]) and np.array_equal(mask, data[c][f - 100][1])
    with pytest.raises(IndexError):
        src.read(112, 0)
    src.close()


def test_lossy_video_codecs_are_refused(tmp_path):
    with pytest.raises(ValueError, match="lossy"):
        VideoWriterSet(tmp_path, ["0"], 8, 8, codec="MJPG")


def test_video_names_padded_differently(tmp_path):
    (tmp_path / "img").mkdir()
    rgb, mask = _frames(1)[0]
    w = VideoWriterSet(tmp_path, ["07"], 32, 24)
    w.write(0, rgb, mask)
    w.close()
    src = VideoSource(tmp_path, ["7"])  # calibration says 7, the file is c_07.avi
    assert np.array_equal(src.read(0, 0)[0], rgb)


def test_mask_folder_overrides_alpha(tmp_path):
    root = tmp_path / "seq" / "rgb_32_24"
    rgb, mask = _frames(1)[0]
    write_image(root, 3, 0, rgb, mask)
    other = (np.arange(24 * 32).reshape(24, 32) % 2 * 255).astype(np.uint8)
    (tmp_path / "fg" / "0").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "fg" / "0" / "image_c_0_f_3.png"), other)
    src = ImageFolderSource(tmp_path / "seq", masks=MaskFolderSource(tmp_path / "fg"))
    r, m = src.read(3, 0)
    assert np.array_equal(r, rgb) and np.array_equal(m, other)
    with pytest.raises(FileNotFoundError, match="image_c_0_f_4"):
        MaskFolderSource(tmp_path / "fg").read_mask(4, 0)
