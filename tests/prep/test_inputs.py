"""stg-prep's checks: every bad input stops with one line `stg-prep: error: <file or camera>: <problem>`,
exit code 2, OUT untouched (not created, or as it was) and no temporary folder left beside it. The
inputs are tiny random videos and frame folders: the checks never need a picture that calibrates."""
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from stg_train.cli.prep import main
from stg_train.prep.inputs import find_clips

from .raw import write_video


def _frames(folder, count, size=(64, 48), seed=0):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for k in range(count):
        cv2.imwrite(str(folder / f"{k}.png"), rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8))
    return folder


def _refused(tmp_path, capsys, argv, names: str, out_before=None):
    """Run stg-prep with argv (VIDEOS and OUT included); assert the refusal (module docstring) and that the
    message names `names` (a regex); returns the message."""
    out = tmp_path / "out"
    try:
        code = main(argv)
    except SystemExit as e:  # refused by the parser
        code = e.code
    assert code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1, err
    assert err[0].startswith("stg-prep: error: "), err[0]
    assert re.search(names, err[0]), err[0]
    if out_before is None:
        assert not out.exists()
    else:
        assert sorted(p.relative_to(out) for p in out.rglob("*")) == out_before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")], "a temporary folder was left"
    return err[0]


@pytest.fixture
def videos(tmp_path):
    """tmp_path/videos with two good 10-frame cameras, cam00.mp4 and cam01/ (PNG frames)."""
    folder = tmp_path / "videos"
    folder.mkdir()
    write_video(folder / "cam00.mp4", 10)
    _frames(folder / "cam01", 10)
    return folder


def _args(tmp_path, *extra):
    return [str(tmp_path / "videos"), str(tmp_path / "out"), "--quiet", *extra]


def test_a_folder_that_is_not_there(tmp_path, capsys):
    _refused(tmp_path, capsys, _args(tmp_path), r"videos: no such folder")


def test_an_empty_file(tmp_path, capsys, videos):
    (videos / "cam02.mp4").write_bytes(b"")
    _refused(tmp_path, capsys, _args(tmp_path), r"cam02\.mp4: the file is empty")


def test_a_file_that_is_not_a_video(tmp_path, capsys, videos):
    (videos / "cam02.mov").write_bytes(np.random.default_rng(0).bytes(5000))
    _refused(tmp_path, capsys, _args(tmp_path), r"cam02\.mov: cannot be opened as a video")


def test_a_frame_that_is_not_an_image(tmp_path, capsys, videos):
    (videos / "cam01" / "0.png").write_bytes(b"not a png")
    _refused(tmp_path, capsys, _args(tmp_path), r"cam01/0\.png: cannot be read as an image")


def test_a_broken_frame_further_on_is_found_before_out_is_written(tmp_path, capsys, videos):
    (videos / "cam01" / "7.png").write_bytes(b"not a png")
    _refused(tmp_path, capsys, _args(tmp_path, "--offsets", "0,0"), r"cam01/7\.png: cannot be read as an image")


def test_a_frame_of_another_size(tmp_path, capsys, videos):
    cv2.imwrite(str(videos / "cam01" / "4.png"), np.zeros((24, 32, 3), np.uint8))
    _refused(tmp_path, capsys, _args(tmp_path, "--offsets", "0,0"), r"cam01/4\.png: frame 4 is 32x24")


def test_a_camera_folder_without_frames(tmp_path, capsys, videos):
    (videos / "cam02").mkdir()
    _refused(tmp_path, capsys, _args(tmp_path), r"cam02: no frames")


def test_one_camera_is_not_a_rig(tmp_path, capsys, videos):
    shutil.rmtree(videos / "cam01")
    _refused(tmp_path, capsys, _args(tmp_path), r"videos: needs at least 2 cameras .* found only cam00\.mp4")


def test_two_sources_of_one_camera(tmp_path, capsys, videos):
    write_video(videos / "cam01.mp4", 10)
    _refused(tmp_path, capsys, _args(tmp_path), r"cam01(\.mp4)?: a second source for camera cam01")


def test_resolutions_that_differ(tmp_path, capsys, videos):
    write_video(videos / "cam02.mp4", 10, size=(80, 48))
    _refused(tmp_path, capsys, _args(tmp_path), r"cam02\.mp4: 80x48, but .*cam00\.mp4 is 64x48")


def test_frame_rates_that_differ(tmp_path, capsys, videos):
    write_video(videos / "cam02.mp4", 10, fps=25.0)
    _refused(tmp_path, capsys, _args(tmp_path), r"cam02\.mp4: 25 fps, but .*cam00\.mp4 is 30 fps")


def test_fps_that_contradicts_the_videos(tmp_path, capsys, videos):
    _refused(tmp_path, capsys, _args(tmp_path, "--fps", "24"), r"cam00\.mp4: 30 fps, but --fps says 24")


def test_a_clip_too_short(tmp_path, capsys, videos):
    write_video(videos / "cam02.mp4", 5)
    _refused(tmp_path, capsys, _args(tmp_path), r"cam02\.mp4: 5 frames, too short: .* at least 8")


def test_offsets_that_leave_too_short_a_common_span(tmp_path, capsys, videos):
    _refused(tmp_path, capsys, _args(tmp_path, "--offsets", "cam01=4"), r"cam01: only 6 frames from offset 4 on")


def test_offsets_of_a_camera_that_is_not_there(tmp_path, capsys, videos):
    _refused(tmp_path, capsys, _args(tmp_path, "--offsets", "cam07=1"), r"--offsets: no camera cam07")


def test_offsets_of_the_wrong_count(tmp_path, capsys, videos):
    _refused(tmp_path, capsys, _args(tmp_path, "--offsets", "1,2,3"), r"--offsets: 3 offsets for 2 cameras")


def test_an_offset_past_the_clip(tmp_path, capsys, videos):
    _refused(tmp_path, capsys, _args(tmp_path, "--offsets", "0,10"), r"cam01: offset 10 outside its 10 frames")


def test_offsets_that_do_not_parse(tmp_path, capsys, videos):
    _refused(tmp_path, capsys, _args(tmp_path, "--offsets", "cam01=x"), r"--offsets: .*whole numbers.*'cam01=x'")


def test_an_out_folder_that_is_not_empty_is_kept(tmp_path, capsys, videos):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "notes.txt").write_text("mine")
    _refused(tmp_path, capsys, _args(tmp_path), r"out: exists and is not empty; .*--force",
             out_before=[Path("notes.txt")])
    assert (tmp_path / "out" / "notes.txt").read_text() == "mine"


def test_an_out_folder_inside_the_videos(tmp_path, capsys, videos):
    assert main([str(videos), str(videos / "prepared"), "--quiet"]) == 2
    assert re.search(r"prepared: inside the folder of videos", capsys.readouterr().err)
    assert not (videos / "prepared").exists()


def test_a_dataset_is_not_raw_videos(tmp_path, capsys, videos):
    np.save(videos / "poses_bounds.npy", np.zeros((2, 17)))
    _refused(tmp_path, capsys, _args(tmp_path), r"videos: holds poses_bounds\.npy, the cameras of a dataset")


def test_cameras_are_named_by_file_and_folder_and_frames_taken_in_number_order(tmp_path, videos):
    for k in (10, 11):
        shutil.copyfile(videos / "cam01" / "0.png", videos / "cam01" / f"{k}.png")
    (videos / "notes.txt").write_text("ignored")
    clips = find_clips(videos)
    assert [(c.name, c.count, c.width, c.height, c.fps) for c in clips] == [
        ("cam00", 10, 64, 48, 30.0), ("cam01", 12, 64, 48, None)]
    assert [p.name for p in clips[1].images][:4] == ["0.png", "1.png", "2.png", "3.png"]
    assert clips[1].images[-1].name == "11.png"


def test_a_folder_of_camera_folders_is_not_a_camera(tmp_path, videos):
    """N3V's frames/camXX beside its videos: stg-prep takes the videos and skips the tree; stg-train reads
    such a folder as an N3V dataset (whose missing poses_bounds.npy it names), not as raw videos."""
    from stg_train.prep.inputs import is_raw_videos

    assert is_raw_videos(videos)
    _frames(videos / "frames" / "cam00", 10)
    assert [c.name for c in find_clips(videos)] == ["cam00", "cam01"]
    assert not is_raw_videos(videos)
