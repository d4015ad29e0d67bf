"""`stg-train VIDEOS/ --out run/` on a folder of raw videos prepares it into run/prep/ first and says so,
trains from there, and reuses run/prep/ on a rerun (remade when the videos change). The training itself
is a stand-in (the pipeline's own tests train)."""
import os
from unittest import mock

import pytest

import stg_train.pipeline
from stg_train.cli.train import main
from stg_train.prep.inputs import is_raw_videos

from .raw import raw_folder

METRICS = {"heldout": {"psnr": 30.0, "ssim": 0.9, "dssim1": 0.05, "dssim2": 0.03, "fps": 100.0, "images": 4,
                       "cameras": ["cam00"]}, "file_bytes": 1000, "gaussians": 100}


@pytest.fixture
def fake_train(monkeypatch):
    stand_in = mock.create_autospec(stg_train.pipeline.train, return_value=METRICS)
    monkeypatch.setattr(stg_train.pipeline, "train", stand_in)
    return stand_in


def test_raw_videos_are_prepared_then_reused(sync_scene, tmp_path, capsys, fake_train):
    n3v, cameras = sync_scene
    raw = raw_folder(n3v, tmp_path / "videos", (1, 0, 2, 0), "mp4")
    assert is_raw_videos(raw) and not is_raw_videos(n3v)  # the N3V folder has its poses
    run = tmp_path / "run"
    assert main([str(raw), "--out", str(run), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert f"stg-train: {raw} holds raw videos: preparing them into {run / 'prep'}" in err
    dataset = fake_train.call_args.args[0]
    assert str(dataset.path) == str(run / "prep")
    assert [c.name for c in dataset.cameras] == [c.name for c in cameras] and dataset.num_frames == 38
    report = run / "prep" / "prep.json"
    made = report.stat().st_mtime_ns

    assert main([str(raw), "--out", str(run), "--quiet", "--force"]) == 0
    assert f"reusing {run / 'prep'}" in capsys.readouterr().err
    assert report.stat().st_mtime_ns == made
    assert str(fake_train.call_args.args[0].path) == str(run / "prep")

    os.utime(raw / "cam03.mp4", ns=(made + 10**9, made + 10**9))  # a changed video: prepared again
    assert main([str(raw), "--out", str(run), "--quiet", "--force"]) == 0
    assert "preparing them into" in capsys.readouterr().err
    assert report.stat().st_mtime_ns != made


def test_a_bad_folder_of_videos_is_an_error_of_stg_train(tmp_path, capsys, fake_train):
    (tmp_path / "videos").mkdir()
    (tmp_path / "videos" / "cam00.mp4").write_bytes(b"")
    (tmp_path / "videos" / "cam01.mp4").write_bytes(b"")
    assert main([str(tmp_path / "videos"), "--out", str(tmp_path / "run"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("stg-train: error: ") and "cam00.mp4: the file is empty" in err[-1]
    assert not fake_train.called and not (tmp_path / "run" / "prep").exists()


def test_an_out_that_is_a_file(sync_scene, tmp_path, capsys, fake_train):
    raw = raw_folder(sync_scene[0], tmp_path / "videos", kind="png")
    (tmp_path / "run").write_text("a file")
    assert main([str(raw), "--out", str(tmp_path / "run"), "--quiet"]) == 2
    assert capsys.readouterr().err.strip().endswith("run: is a file, not a folder")
    assert (tmp_path / "run").read_text() == "a file" and not fake_train.called
