"""``deliffas ingest`` on the real Pose2Sim recording (four cameras), a few frames, and its errors."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from deliffas.cli import main
from deliffas.data.ingest import IngestConfig, ingest
from deliffas.data.ingest.detect import KEYPOINT_NAMES
from deliffas.data.subjects import parse_subject

REAL = Path(__file__).resolve().parents[3] / "shared" / "real-captures" / "pose2sim-demo"
needs_real = pytest.mark.skipif(not (REAL / "videos").is_dir(),
                                reason="the Pose2Sim demo recording is not at ../shared/real-captures/")


def _have_detector() -> bool:
    try:
        from deliffas.data.ingest.detect import require_detector

        require_detector()
        return True
    except ValueError:
        return False


needs_detector = pytest.mark.skipif(not _have_detector(), reason="MediaPipe 0.10.21 is not installed "
                                                                  "(make ingest-setup)")


@pytest.fixture(scope="module")
def ingested(tmp_path_factory) -> Path:
    if not (REAL / "videos").is_dir() or not _have_detector():
        pytest.skip("needs the shared recording and the detector")
    out = tmp_path_factory.mktemp("ingest") / "subject"
    ingest(IngestConfig(str(REAL), str(out), frames="40:52:2", size=320, min_frames=4, overlays=1, progress=False,
                        fit_iters=100))
    return out


@needs_real
@needs_detector
def test_the_real_recording_becomes_a_subject_the_pipeline_reads(ingested):
    report = json.loads((ingested / "ingest_report.json").read_text())
    assert report["frames"]["read"] == 6 and report["frames"]["fitted"] >= 5
    assert [c["camera"] for c in report["cameras"]] == ["cam01", "cam02", "cam03", "cam04"]
    assert all(c["detector_person_fraction"] == 1.0 for c in report["cameras"])
    assert report["keypoints"]["median_px"] < 6.0  # at 180 x 320
    assert report["fit"]["median_silhouette_iou"] > 0.6
    assert report["image_size"] == [180, 320]
    assert (ingested / report["overlays"][0]).is_file() and not (ingested / ".ingest").exists()
    subject = parse_subject(ingested)
    assert subject.format == "dynacap" and subject.test_cameras == (3,)
    assert set(subject.sequences) == {"training", "testing"}
    seq = subject.sequences["training"]
    assert (seq.width, seq.height) == (180, 320) and seq.poses is not None
    with np.load(ingested / "keypoints.npz") as kp:  # the 2-D and 3-D keypoints stay with the subject
        J = len(KEYPOINT_NAMES)
        assert kp["keypoints2d"].shape == (4, 6, J, 2) and kp["points3d"].shape == (6, J, 3)
        assert list(kp["frames"]) == [40, 42, 44, 46, 48, 50] and list(kp["camera_names"])[0] == "cam01"
        assert kp["valid3d"].mean() > 0.9


@needs_real
@needs_detector
def test_check_scores_the_fitted_body_against_the_masks(ingested, tmp_path):
    code = main(["check", str(ingested), "--out", str(tmp_path / "check")])
    summary = json.loads((tmp_path / "check" / "summary.json").read_text())
    assert code in (0, 1) and summary  # the verdict depends on the few frames; the scoring must run


@needs_real
@needs_detector
def test_bad_input_is_one_error_line_before_any_work(tmp_path, capsys):
    rec = tmp_path / "rec"
    (rec / "videos").mkdir(parents=True)
    shutil.copy(REAL / "calibration" / "Calib.qca.txt", rec / "Calib.qca.txt")
    for n in ("cam01", "cam02", "cam03"):
        (rec / "videos" / f"{n}.mp4").symlink_to(REAL / "videos" / f"{n}.mp4")
    assert main(["ingest", str(rec), "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert "cam04" in err and "error:" in err and "Traceback" not in err
    assert not (tmp_path / "s").exists()
    (rec / "videos" / "cam04.mp4").write_bytes(b"not a video")
    assert main(["ingest", str(rec), "--out", str(tmp_path / "s")]) == 2
    assert "cam04.mp4" in capsys.readouterr().err and not (tmp_path / "s").exists()


@needs_real
def test_a_missing_detector_names_the_extra(tmp_path, capsys, monkeypatch):
    import deliffas.data.ingest.detect as detect

    def no_module(module, need):
        raise ImportError(f"{need} (No module named {module!r})")

    monkeypatch.setattr(detect, "import_optional", no_module)
    assert main(["ingest", str(REAL), "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert "deliffas[ingest]" in err and "mediapipe==0.10.21" in err and not (tmp_path / "s").exists()


@needs_real
@needs_detector
def test_an_interrupted_ingest_resumes_without_detecting_again(tmp_path, monkeypatch):
    import deliffas.data.ingest.pipeline as pipeline
    import deliffas.data.ingest.stages as stages

    out = tmp_path / "s"
    cfg = IngestConfig(str(REAL), str(out), frames="0:8:2", size=160, min_frames=2, overlays=1, progress=False,
                       cameras="cam01,cam02,cam03", test_cameras=1, fit_iters=40)

    def crash(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "fit_stage", crash)
    with pytest.raises(KeyboardInterrupt):
        ingest(cfg)
    assert (out / ".ingest" / "keypoints3d.npz").is_file()
    assert not (out / "cameras.calibration").exists() and not (out / "ingest_report.json").exists()
    with pytest.raises(FileExistsError, match="--resume"):
        ingest(cfg)
    with pytest.raises(ValueError, match="other settings"):
        ingest(dataclasses.replace(cfg, resume=True, size=200))
    monkeypatch.undo()

    def no_detection(*args, **kwargs):
        raise AssertionError("detection ran again")

    monkeypatch.setattr(stages, "PersonDetector", no_detection)
    ingest(dataclasses.replace(cfg, resume=True))
    assert (out / "ingest_report.json").is_file() and (out / "cameras.calibration").is_file()
    with pytest.raises(FileExistsError, match="--overwrite"):
        ingest(cfg)
