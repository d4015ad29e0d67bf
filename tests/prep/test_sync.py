"""Synchronisation: clips of the synthetic scene whose starts are cut 0-5 frames apart (cameras that
started recording late) get their offsets back exactly, from PNG frame folders and from mp4 videos, and
the written frame k of every camera is the same moment; offsets given by hand are used as given; a
camera with nothing moving is a low-confidence warning naming it."""
import json
import shutil

import cv2
import numpy as np
import pytest

from stg_train.cli.prep import main
from stg_train.data import load_dataset
from stg_train.data.layouts import detect_layout
from stg_train.prep import prepare
from stg_train.prep.sync import LOW_CONFIDENCE, estimate_offsets

from .raw import raw_folder


def _expected(cuts):
    """A camera that started cut frames late skips that many fewer frames than the latest one."""
    return [max(cuts) - c for c in cuts]


@pytest.mark.parametrize("kind, cuts", [("png", (3, 0, 5, 1)), ("mp4", (0, 4, 2, 5))])
def test_offsets_are_recovered_exactly(sync_scene, tmp_path, kind, cuts):
    n3v, cameras = sync_scene
    raw = raw_folder(n3v, tmp_path / "videos", cuts, kind)
    report = prepare(raw, tmp_path / "out")
    assert [c["offset"] for c in report["cameras"]] == _expected(cuts)
    assert all(c["confidence"] >= LOW_CONFIDENCE for c in report["cameras"]), report["cameras"]
    assert report["warnings"] == []
    # trimmed to the span every camera has: 40 - max(cuts) frames
    assert report["frames"] == 40 - max(cuts)
    assert len(report["trimmed"]) == sum(1 for c in cuts if c < max(cuts))  # those that skip frames
    assert json.loads((tmp_path / "out" / "prep.json").read_text())["frames"] == report["frames"]
    if kind == "png":  # lossless: written frame k of camera c is the scene's frame max(cuts) + k
        for cam in cameras:
            for k in (0, report["frames"] - 1):
                written = cv2.imread(str(tmp_path / "out" / "images" / cam.name / f"{k:05d}.png"))
                original = cv2.imread(str(n3v / "frames" / cam.name / f"{max(cuts) + k:06d}.png"))
                assert np.array_equal(written, original), (cam.name, k)


def test_the_prepared_folder_loads_as_a_rig(sync_scene, tmp_path, capsys):
    n3v, cameras = sync_scene
    raw = raw_folder(n3v, tmp_path / "videos", (2, 0, 1, 0), "png")
    assert main([str(raw), str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "stg-prep: 4 cameras x 38 frames, 160x120 at 30 fps" in err
    assert "stg-prep calibrate" in err and "stg-prep write" in err  # the progress bars
    assert detect_layout(tmp_path / "out") == "rig"
    dataset = load_dataset(tmp_path / "out")
    assert [c.name for c in dataset.cameras] == [c.name for c in cameras]
    assert dataset.num_frames == 38 and dataset.fps == 30.0
    assert all((c.width, c.height, c.model) == (160, 120, "pinhole") for c in dataset.cameras)
    assert dataset.bounds is not None  # from the model's 3D points


def test_offsets_given_by_hand_are_used(sync_scene, tmp_path):
    n3v, _ = sync_scene
    raw = raw_folder(n3v, tmp_path / "videos", (0, 0, 0, 0), "png")
    report = prepare(raw, tmp_path / "out", offsets={"cam02": 3})
    assert [(c["offset"], c["confidence"]) for c in report["cameras"]] == [(0, None), (0, None), (3, None), (0, None)]
    assert report["sync"]["method"] == "given" and report["frames"] == 37
    assert cv2.imread(str(tmp_path / "out" / "images" / "cam02" / "00000.png")).tobytes() == \
        cv2.imread(str(n3v / "frames" / "cam02" / "000003.png")).tobytes()


def test_a_camera_that_sees_nothing_move_is_a_warning(sync_scene, tmp_path, capsys):
    n3v, _ = sync_scene
    raw = raw_folder(n3v, tmp_path / "videos", (0, 0, 0, 0), "png")
    for k in range(1, 40):  # a frozen picture: no motion, no change of brightness
        shutil.copyfile(raw / "cam03" / "0.png", raw / "cam03" / f"{k}.png")
    assert main([str(raw), str(tmp_path / "out"), "--quiet"]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(warnings) == 1 and warnings[0].startswith("stg-prep: warning: cam03: offset 0 found with a low "
                                                         "confidence 0.00"), warnings
    report = json.loads((tmp_path / "out" / "prep.json").read_text())
    assert [c["offset"] for c in report["cameras"]] == [0, 0, 0, 0]
    assert report["warnings"] and "cam03" in report["warnings"][0]


def test_a_periodic_signal_has_no_confidence():
    """Two cameras whose signal repeats every 4 frames: every lag 4 apart fits as well."""
    t = np.arange(40)
    wave = np.stack([np.sin(2 * np.pi * t / 4), np.cos(2 * np.pi * t / 4)], axis=1)
    (o0, c0), (o1, c1) = estimate_offsets([wave, np.roll(wave, 1, axis=0)], 10)
    assert c0 < LOW_CONFIDENCE and c1 < LOW_CONFIDENCE


def test_a_video_that_holds_fewer_frames_than_it_states(sync_scene, tmp_path):
    """A truncated AVI states 40 frames in its header and decodes fewer: the frames it has are used, and
    the report says so."""
    n3v, _ = sync_scene
    raw = raw_folder(n3v, tmp_path / "videos", (0, 0, 0, 0), "png")
    writer = cv2.VideoWriter(str(raw / "cam03.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (160, 120))
    for k in range(40):
        writer.write(cv2.imread(str(raw / "cam03" / f"{k}.png")))
    writer.release()
    shutil.rmtree(raw / "cam03")
    data = (raw / "cam03.avi").read_bytes()
    (raw / "cam03.avi").write_bytes(data[:int(len(data) * 0.85)])
    report = prepare(raw, tmp_path / "out", offsets=[0, 0, 0, 0])
    decoded = report["frames"]
    assert 8 <= decoded < 40
    assert report["cameras"][3]["frames"] == decoded
    assert any(f"cam03.avi: states 40 frames, {decoded} decode" in w for w in report["warnings"]), report["warnings"]
    assert len(list((tmp_path / "out" / "images" / "cam00").iterdir())) == decoded


def test_a_degenerate_fit_is_mapped_again_on_one_thread(sync_scene, tmp_path, monkeypatch):
    """A fit with an implausible focal length (as pycolmap's threaded mapper once gave under load) is
    mapped once more on one thread, and that fit is the one written."""
    import stg_train.prep.calibrate as calibrate

    found, real = [], calibrate.implausible_focal

    def first_fit_degenerate(rec, width):
        found.append(width)
        return ("cam01", -5.0) if len(found) == 1 else real(rec, width)

    monkeypatch.setattr(calibrate, "implausible_focal", first_fit_degenerate)
    n3v, _ = sync_scene
    raw = raw_folder(n3v, tmp_path / "videos", (2, 0, 1, 0), "png")
    assert main([str(raw), str(tmp_path / "out"), "--quiet"]) == 0
    assert len(found) == 3  # per camera: the degenerate fit and its refit; then the shared intrinsics
    assert all(c.model == "pinhole" and 80 < c.fx < 480 for c in load_dataset(tmp_path / "out").cameras)
