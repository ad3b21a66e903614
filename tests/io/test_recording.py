"""Raw recordings: streams found (videos, image folders), matched to camera names, checked, and read frame by frame;
the real Pose2Sim demo videos (h264 and vp9) read at frames 0, 50 and 99."""

from __future__ import annotations

import logging
from dataclasses import replace
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from deliffas.io.recording import (RecordingError, Stream, StreamReader, check_streams, find_streams, match_streams,
                                   parse_frame_range)

av = pytest.importorskip("av")
cv2 = pytest.importorskip("cv2")

REAL = Path(__file__).resolve().parents[3] / "shared" / "real-captures" / "pose2sim-demo"
W, H = 64, 48
STEP = 20  # frame i is a flat grey of level STEP * i: the counter the tests read back


def _level(i: int) -> int:
    return STEP * i


def write_video(path: Path, n: int, fps: float = 10, codec: str = "mpeg4", size: tuple[int, int] = (W, H),
                noise: bool = False) -> Path:
    """A video of ``n`` flat frames (frame i of grey level STEP * i), or of random frames (``noise``: big packets)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    w, h = size
    rng = np.random.default_rng(0)
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height = w, h
        stream.pix_fmt = "yuv444p" if codec == "ffv1" else "yuv420p"
        for i in range(n):
            rgb = rng.integers(0, 256, (h, w, 3), np.uint8) if noise else np.full((h, w, 3), _level(i), np.uint8)
            frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def write_images(folder: Path, n: int, size: tuple[int, int] = (W, H), name: str = "{}.png") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    w, h = size
    for i in range(n):
        assert cv2.imwrite(str(folder / name.format(i)), np.full((h, w, 3), _level(i), np.uint8))
    return folder


def levels(reader: StreamReader, indices: range) -> list[tuple[int, int]]:
    """(index, the frame's mean grey level rounded to the counter's step) of each frame read."""
    out = []
    for i, rgb in reader.frames(indices):
        assert rgb.shape == (reader.stream.height, reader.stream.width, 3) and rgb.dtype == np.uint8
        assert np.ptp(rgb.astype(int)) <= 6, "a flat frame came back with structure"
        out.append((i, int(round(rgb.mean() / STEP))))
    return out


def fake(key: str, n: int = 10, fps: float | None = 10.0, camera: str = "") -> Stream:
    return Stream(camera, Path("rec") / "videos" / f"{key}.mp4", "video", n, fps, W, H)


# ------------------------------------------------------------------------------------------------ find_streams


def test_videos_in_videos_folder_any_case_natural_order(tmp_path):
    write_video(tmp_path / "videos" / "cam10.MP4", 10)
    write_video(tmp_path / "videos" / "cam2.avi", 10, fps=12.5)
    write_video(tmp_path / "videos" / "cam3.mkv", 7, codec="ffv1")  # mkv states no frame count: demuxed
    (tmp_path / "videos" / "notes.txt").write_text("not a video")
    streams = find_streams(tmp_path)
    assert [s.path.name for s in streams] == ["cam2.avi", "cam3.mkv", "cam10.MP4"]
    assert [s.num_frames for s in streams] == [10, 7, 10]
    assert [s.fps for s in streams] == [pytest.approx(12.5), pytest.approx(10), pytest.approx(10)]
    assert all((s.kind, s.width, s.height, s.camera) == ("video", W, H, "") for s in streams)


def test_videos_in_the_folder_itself(tmp_path):
    write_video(tmp_path / "a.mov", 3)
    (tmp_path / "calibration").mkdir()
    (tmp_path / "calibration" / "Calib.toml").write_text("")
    assert [s.path for s in find_streams(tmp_path)] == [tmp_path / "a.mov"]


@pytest.mark.parametrize("images", ["images", "."])
def test_image_folders(tmp_path, images):
    base = tmp_path / images
    write_images(base / "cam1", 12, name="frame{}.png")  # frame10.png after frame2.png
    write_images(base / "cam0", 12, size=(32, 24), name="{}.jpg")
    (tmp_path / "calibration").mkdir()
    (tmp_path / "calibration" / "calib.json").write_text("{}")
    streams = find_streams(tmp_path)
    assert [(s.path.name, s.kind, s.num_frames, s.fps, s.width, s.height) for s in streams] == [
        ("cam0", "images", 12, None, 32, 24), ("cam1", "images", 12, None, W, H)]
    with StreamReader(streams[1]) as reader:
        assert levels(reader, range(0, 12, 5)) == [(0, 0), (5, 5), (10, 10)]


def test_no_streams_and_no_folder(tmp_path):
    (tmp_path / "videos").mkdir()
    with pytest.raises(RecordingError, match=r"no camera streams found.*videos.*images"):
        find_streams(tmp_path)
    with pytest.raises(RecordingError, match="recording folder not found"):
        find_streams(tmp_path / "absent")


def test_unreadable_video_is_named(tmp_path):
    write_video(tmp_path / "videos" / "cam1.mp4", 3)
    bad = tmp_path / "videos" / "cam2.mp4"
    bad.write_bytes(b"\0not a video" * 100)
    with pytest.raises(RecordingError, match=r"cam2\.mp4: not a readable video"):
        find_streams(tmp_path)


def test_unreadable_first_image_is_named(tmp_path):
    folder = write_images(tmp_path / "images" / "cam1", 3)
    (folder / "0.png").write_bytes(b"garbage")
    with pytest.raises(RecordingError, match=r"0\.png: not a readable image"):
        find_streams(tmp_path)


# ------------------------------------------------------------------------------------------------ match_streams


def test_match_tiers_and_extras(caplog):
    streams = [fake("Camera_1"), fake("cam02"), fake("LEFT"), fake("rig_side_view"), fake("spare")]
    with caplog.at_level(logging.INFO, logger="deliffas.io.recording"):
        matched = match_streams(["side", "left", "cam2", "cam01"], streams)
    assert [(s.camera, s.key) for s in matched] == [("side", "rig_side_view"), ("left", "LEFT"),
                                                   ("cam2", "cam02"), ("cam01", "Camera_1")]
    assert "spare.mp4" in caplog.text and "ignoring 1" in caplog.text


def test_match_prefers_exact_and_resolves_by_elimination():
    streams = [fake("cam1"), fake("cam01")]
    assert [s.key for s in match_streams(["cam01", "cam1"], streams)] == ["cam01", "cam1"]
    # "1" is inside both names; once "11" takes cam_11, cam_1 is the only one left
    streams = [fake("cam_11"), fake("cam_1")]
    assert [s.key for s in match_streams(["1", "11"], streams)] == ["cam_1", "cam_11"]


def test_ambiguous_and_missing_cameras_are_tabulated():
    streams = [fake("cam1_left"), fake("cam1_right"), fake("cam2")]
    with pytest.raises(RecordingError) as err:
        match_streams(["cam1", "cam2", "cam3"], streams)
    text = str(err.value)
    assert "cannot match 2 of the 3 calibration cameras (cam1, cam3)" in text
    assert "cam1    AMBIGUOUS: cam1_left.mp4, cam1_right.mp4" in text
    assert "cam2    cam2.mp4" in text and "cam3    MISSING" in text
    assert "Rename the files" in text and "--cameras NAME,..." in text


def test_one_stream_wanted_by_two_cameras_is_ambiguous():
    with pytest.raises(RecordingError, match=r"cam1 +AMBIGUOUS: cam001\.mp4(.|\n)*cam01 +AMBIGUOUS: cam001\.mp4"):
        match_streams(["cam1", "cam01"], [fake("cam001")])


# ------------------------------------------------------------------------------------------------ frame ranges


@pytest.mark.parametrize("text,want", [("0:10", (0, 10, 1)), ("5:20:3", (5, 20, 3)), (":8", (0, 8, 1)),
                                       ("7:", (7, -1, 1)), ("2::4", (2, -1, 4)), (" 1:2 ", (1, 2, 1))])
def test_parse_frame_range(text, want):
    assert parse_frame_range(text) == want


@pytest.mark.parametrize("text", ["5", "a:b", "1:2:3:4", "-1:5", "5:5", "6:2", "0:10:0", ""])
def test_parse_frame_range_refuses(text):
    with pytest.raises(ValueError, match="expected A:B or A:B:STEP"):
        parse_frame_range(text)


def test_check_streams_lengths_and_cut():
    same = [fake("a", 10), fake("b", 10)]
    assert check_streams(same, None) == range(10)
    assert check_streams(same, (3, -1, 2)) == range(3, 10, 2)
    uneven = [fake("a", 10, camera="cam01"), fake("b", 8, camera="cam02")]
    with pytest.raises(RecordingError) as err:
        check_streams(uneven, None)
    assert "cam01  a.mp4: 10 frames, 10 fps" in str(err.value) and "cam02  b.mp4: 8 frames" in str(err.value)
    assert "--frames 0:8 " in str(err.value)
    assert check_streams(uneven, (0, 8, 2)) == range(0, 8, 2)  # within every stream: fine
    with pytest.raises(RecordingError, match="different frame counts"):
        check_streams(uneven, (2, -1, 1))
    with pytest.raises(RecordingError, match=r"--frames 0:9 reaches past the end(.|\n)*B <= 8 \(e\.g\. --frames 0:8"):
        check_streams(uneven, (0, 9, 1))
    with pytest.raises(RecordingError, match="past the end"):
        check_streams(same, (10, -1, 1))


def test_check_streams_fps():
    with pytest.raises(RecordingError, match=r"different frame rates(.|\n)*30 fps(.|\n)*29\.97 fps"):
        check_streams([fake("a", fps=30), fake("b", fps=29.97)], (0, 5, 1))
    images = [replace(fake("a"), kind="images", fps=None), replace(fake("b"), kind="images", fps=None)]
    assert check_streams(images, None) == range(10)


# ------------------------------------------------------------------------------------------------ StreamReader


@pytest.mark.parametrize("name,codec", [("v.avi", "mpeg4"), ("v.mkv", "ffv1"), ("v.mp4", "mpeg4")])
def test_reader_selects_frames_forward(tmp_path, name, codec):
    write_video(tmp_path / name, 10, codec=codec)
    (stream,) = find_streams(tmp_path)
    with StreamReader(stream) as reader:
        assert levels(reader, range(1, 10, 3)) == [(1, 1), (4, 4), (7, 7)]
        assert levels(reader, range(8, 10)) == [(8, 8), (9, 9)]  # continues forward
        assert levels(reader, range(0, 3, 2)) == [(0, 0), (2, 2)]  # earlier frames: reopened from the start
    assert reader._container is None


def test_video_ending_early(tmp_path):
    write_video(tmp_path / "cam1.mp4", 10)
    (stream,) = find_streams(tmp_path)
    with StreamReader(replace(stream, num_frames=20)) as reader:
        got = []
        with pytest.raises(RecordingError, match=r"cam1\.mp4: the video ends after 10 frames, frame 12 was asked for"
                                                 r".*claims 20.*B <= 10"):
            for i, _ in reader.frames(range(0, 20, 4)):
                got.append(i)
    assert got == [0, 4, 8]


def test_truncated_video(tmp_path):
    path = write_video(tmp_path / "cam1.avi", 10, noise=True)
    data = path.read_bytes()
    path.write_bytes(data[:len(data) * 2 // 3])
    (stream,) = find_streams(tmp_path)
    assert stream.num_frames == 10  # the AVI header still states 10 frames
    ends = r"cam1\.avi: the video ends after \d frames, frame \d was asked for .*claims 10"
    with StreamReader(stream) as reader, pytest.raises(RecordingError, match=ends):
        for _ in reader.frames(range(0, 10, 3)):
            pass


def test_unreadable_or_resized_image_mid_folder(tmp_path):
    folder = write_images(tmp_path / "images" / "cam1", 4)
    (folder / "2.png").write_bytes(b"garbage")
    cv2.imwrite(str(folder / "3.png"), np.zeros((H, W + 2, 3), np.uint8))
    (stream,) = find_streams(tmp_path)
    with StreamReader(stream) as reader:
        assert levels(reader, range(2)) == [(0, 0), (1, 1)]
        with pytest.raises(RecordingError, match=r"2\.png: not a readable image"):
            list(reader.frames(range(2, 3)))
        with pytest.raises(RecordingError, match=r"3\.png: frame 3 is 66x48"):
            list(reader.frames(range(3, 4)))


# ------------------------------------------------------------------------------------------------ the real recording


@pytest.mark.skipif(not (REAL / "videos").is_dir(), reason="the Pose2Sim demo recording is not at "
                                                           "../shared/real-captures/pose2sim-demo")
def test_real_recording_frames_0_50_99():
    streams = match_streams(["cam01", "cam02", "cam03", "cam04"], find_streams(REAL))
    assert [(s.camera, s.path.name, s.num_frames, s.fps, s.width, s.height) for s in streams] == [
        ("cam01", "cam01.mp4", 100, 60.0, 1080, 1920), ("cam02", "cam02.mp4", 100, 60.0, 1080, 1920),
        ("cam03", "cam03.mp4", 100, 60.0, 1088, 1920), ("cam04", "cam04.mp4", 100, 60.0, 1088, 1920)]
    assert check_streams(streams, None) == range(100)
    for stream in streams:
        with StreamReader(stream) as reader:
            got = list(reader.frames(range(0, 100, 50))) + list(reader.frames(range(99, 100)))
        assert [i for i, _ in got] == [0, 50, 99]
        for _, rgb in got:
            assert rgb.shape == (1920, stream.width, 3) and rgb.dtype == np.uint8 and rgb.std() > 20
        assert np.abs(got[0][1].astype(int) - got[2][1]).mean() > 1  # the person moved: different frames
