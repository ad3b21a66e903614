"""write_video: H.264 .mp4 and MJPEG .avi that read back, odd sizes padded, and no partial or temporary file on failure."""

from __future__ import annotations

import numpy as np
import pytest

from deliffas.io.video import read_video_info, write_video

pytest.importorskip("av")


def _frames(n: int, h: int = 24, w: int = 32):
    for i in range(n):
        yield np.full((h, w, 3), 20 * i, np.uint8)


@pytest.mark.parametrize("suffix,codec", [(".mp4", "h264"), (".avi", "mjpeg")])
def test_written_video_reads_back(tmp_path, suffix, codec):
    out = tmp_path / f"v{suffix}"
    assert write_video(out, _frames(5), fps=10) == 5
    info = read_video_info(out)
    assert info["codec"] == codec and info["frames"] == 5 and (info["width"], info["height"]) == (32, 24)
    assert info["fps"] == pytest.approx(10)
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]


def test_odd_size_is_padded(tmp_path):
    write_video(tmp_path / "odd.mp4", _frames(2, 23, 31), fps=5)
    info = read_video_info(tmp_path / "odd.mp4")
    assert (info["width"], info["height"]) == (32, 24)


def _bad_after_two():
    yield from _frames(2)
    yield np.zeros((24, 32, 3), np.float32)


@pytest.mark.parametrize("frames,match", [([], "no frames"), (_bad_after_two, "frame 2: expected"),
                                          (lambda: [np.zeros((24, 32, 3), np.uint8), np.zeros((24, 30, 3), np.uint8)],
                                           "frame 1: shape")])
def test_failure_leaves_the_old_file_and_no_temporary(tmp_path, frames, match):
    out = tmp_path / "v.mp4"
    out.write_bytes(b"the old video")
    with pytest.raises(ValueError, match=match):
        write_video(out, frames() if callable(frames) else frames, fps=10)
    assert out.read_bytes() == b"the old video"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="must end in"):
        write_video(tmp_path / "v.gif", _frames(1), fps=10)
    with pytest.raises(ValueError, match="fps"):
        write_video(tmp_path / "v.mp4", _frames(1), fps=0)
    assert not any(tmp_path.iterdir())
