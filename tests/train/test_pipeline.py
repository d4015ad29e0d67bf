"""The trainer end to end on a tiny synthetic scene (CPU): quality, dynamic vs static, export to the
runtime, resume after an interruption, and the command lines' error handling."""
from __future__ import annotations

import json

import pytest

torch = pytest.importorskip("torch")

from stg_runtime.atomic import TEMPORARY_PATTERN, temporary_path  # noqa: E402
from stg_runtime.player import Player  # noqa: E402
from stg_train.cli.eval import main as eval_main  # noqa: E402
from stg_train.cli.train import main as train_main  # noqa: E402
from stg_train.data import load_n3v  # noqa: E402
from stg_train.export import GoldenDiff, export_trainer, trainer_render  # noqa: E402
from stg_train.trainer import Trainer, TrainConfig  # noqa: E402

# A tiny scene whose dynamics matter: 8 frames over 2 s (4 fps), so the sphere travels across the room,
# the box turns by 2.4 rad and the fader appears and vanishes within the clip.
SCENE = dict(num_cameras=5, num_frames=8, fps=4.0, width=64, height=48)
TRAIN = dict(iterations=300, num_points=2000, schedule={"refine_start": 30, "refine_every": 20, "reset_every": 0})
#: Measured held-out PSNR (dB) with TRAIN on a 2-core CPU: dynamic 29.1, static 25.7 (margin 3.4).
MIN_PSNR = 27.5
MIN_MARGIN = 2.0


pytestmark = pytest.mark.usefixtures("two_torch_threads")


@pytest.fixture(scope="module")
def scene_dir(synthetic_n3v):
    return synthetic_n3v("tiny_scene", **SCENE)


@pytest.fixture(scope="module")
def dataset(scene_dir):
    return load_n3v(scene_dir, prefer_png=True)


@pytest.fixture(scope="module")
def dynamic(dataset):
    trainer = Trainer(dataset, TrainConfig(**TRAIN))
    trainer.train(progress=False)
    return trainer


@pytest.fixture(scope="module")
def static(dataset):
    trainer = Trainer(dataset, TrainConfig(**TRAIN, static=True))
    trainer.train(progress=False)
    return trainer


def test_training_reaches_psnr(dynamic):
    psnr = dynamic.heldout_psnr()
    print(f"held-out PSNR {psnr:.2f} dB, {dynamic.params.count} Gaussians")
    assert psnr >= MIN_PSNR


def test_dynamic_beats_static(dynamic, static):
    dyn, sta = dynamic.heldout_psnr(), static.heldout_psnr()
    print(f"held-out PSNR: dynamic {dyn:.2f} dB, static {sta:.2f} dB, margin {dyn - sta:.2f} dB")
    assert dyn - sta >= MIN_MARGIN
    # the static model really is static: its time parameters never moved
    raw = static.params.raw
    assert torch.all(raw["motion"] == 0) and torch.all(raw["omega"] == 0) and torch.all(raw["time_features"] == 0)


def test_export_matches_player(dynamic, dataset, tmp_path):
    report = export_trainer(dynamic, tmp_path / "model.stg")  # raises when the check fails
    assert report.diff is not None and report.diff.ok
    player = Player(tmp_path / "model.stg", device="cpu")
    assert player.num_frames == dataset.num_frames and player.fps == dataset.fps
    assert player.model.provenance["tool"] == "stg-train"
    cam = dataset.cameras[dataset.test_cameras[0]]
    for j in range(dataset.num_frames):
        ours = trainer_render(dynamic.params, cam, j / dataset.num_frames)
        diff = GoldenDiff.of(player.render(cam, j / dataset.fps), ours)
        assert diff.ok and diff.max_abs < 0.01, diff


def test_export_lite(dataset, tmp_path):
    trainer = Trainer(dataset, TrainConfig(model="lite", iterations=20, num_points=500))
    trainer.train(progress=False)
    report = export_trainer(trainer, tmp_path / "lite.stg")
    assert Player(report.path).kind == "lite" and report.diff.ok


class _Killed(Exception):
    pass


def _assert_same_state(a: Trainer, b: Trainer) -> None:
    assert a.step == b.step and a.params.count == b.params.count
    for name in a.params.raw:
        assert torch.equal(a.params.raw[name], b.params.raw[name]), name
    for pa, pb in zip(a.params.decoder.parameters(), b.params.decoder.parameters()):
        assert torch.equal(pa, pb)
    sa, sb = a.optimizer.state_dict(), b.optimizer.state_dict()
    assert sa["param_groups"] == sb["param_groups"]
    for k in sa["state"]:
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(sa["state"][k][key], sb["state"][k][key])
    assert a.rng.bit_generator.state == b.rng.bit_generator.state


def test_resume_after_kill_reaches_same_state(dataset, tmp_path):
    # densification at steps 12 and 18, an opacity reset at 15: both sides of the interruption
    cfg = dict(iterations=24, num_points=400, checkpoint_every=10,
               schedule={"refine_start": 10, "refine_every": 6, "densify_rounds": 2, "reset_every": 15,
                         "reset_until": 15})
    straight = Trainer(dataset, TrainConfig(**cfg), out_dir=tmp_path / "a")
    straight.train(progress=False)

    def kill(trainer):
        if trainer.step == 13:  # three steps after the checkpoint at 10
            raise _Killed

    run = Trainer(dataset, TrainConfig(**cfg), out_dir=tmp_path / "b")
    with pytest.raises(_Killed):
        run.train(progress=False, callback=kill)
    resumed = Trainer.resume(dataset, tmp_path / "b" / "checkpoint.pt")
    assert resumed.step == 10
    resumed.train(progress=False)
    assert straight.strategies[0].rounds_done == 2
    _assert_same_state(straight, resumed)
    assert not [p for p in (tmp_path / "b").iterdir() if TEMPORARY_PATTERN.match(p.name)]


def test_cli_trains_and_evaluates(scene_dir, tmp_path, capsys):
    out = tmp_path / "run"
    assert train_main([str(scene_dir), "--out", str(out), "--iterations", "10", "--points", "300", "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == 10 and metrics["export_check"]["max_abs"] <= 2e-2
    assert (out / "model.stg").exists() and (out / "checkpoint.pt").exists()
    capsys.readouterr()
    assert eval_main([str(out / "model.stg"), str(scene_dir), "--json", str(tmp_path / "eval.json"), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "PSNR" in printed and "DSSIM2" in printed and "PSNR dynamic / static (dB)" in printed
    figures = json.loads((tmp_path / "eval.json").read_text())
    assert abs(figures["psnr"] - metrics["heldout"]["psnr"]) < 1e-6
    for key in ("dynamic_psnr", "static_psnr", "dynamic_ssim", "static_ssim"):  # the scene moves: both regions
        assert abs(figures[key] - metrics["heldout"][key]) < 1e-6
    assert 0.05 < figures["dynamic_fraction"] < 0.6 and figures["dynamic_threshold"] == 0.1
    assert len(figures["per_frame"]) == SCENE["num_frames"]


def test_stg_eval_aligns_a_held_out_pose_that_is_off(dynamic, scene_dir, tmp_path, capsys):
    import shutil

    import numpy as np

    from stg_train.rotations import rotation_from_axis_angle

    export_trainer(dynamic, tmp_path / "model.stg")
    off = tmp_path / "off"  # the same scene, its held-out camera's stated pose turned by 1.5 degrees
    shutil.copytree(scene_dir, off, ignore=shutil.ignore_patterns(".stg_cache"))
    poses = np.load(off / "poses_bounds.npy")
    camera_to_world = poses[0, :15].reshape(3, 5)
    camera_to_world[:, :3] = rotation_from_axis_angle(np.radians(1.5) * np.array([0.6, 0.8, 0.0])) @ camera_to_world[:, :3]
    poses[0, :15] = camera_to_world.reshape(-1)
    np.save(off / "poses_bounds.npy", poses)
    common = [str(tmp_path / "model.stg"), "--no-lpips", "--quiet", "--json"]
    assert eval_main(common + [str(tmp_path / "true.json"), str(scene_dir)]) == 0
    assert eval_main(common + [str(tmp_path / "off.json"), str(off), "--any-cameras"]) == 0
    assert eval_main(common + [str(tmp_path / "aligned.json"), str(off), "--any-cameras", "--align-poses"]) == 0
    assert "stg-eval: cam00's pose aligned to its pictures: moved 1." in capsys.readouterr().err
    true, stated, aligned = (json.loads((tmp_path / f"{name}.json").read_text()) for name in ("true", "off", "aligned"))
    pose = np.array(aligned["aligned_poses"]["cam00"]["world_to_camera"])[:3, :3]
    turn = pose @ load_n3v(scene_dir, prefer_png=True).cameras[0].R.T
    print(f"PSNR at the true pose {true['psnr']:.2f}, turned {stated['psnr']:.2f}, aligned {aligned['psnr']:.2f} dB; "
          f"aligned {np.degrees(np.arccos((np.trace(turn) - 1) / 2)):.3f} degrees from the truth")
    assert np.degrees(np.arccos(min(1.0, (np.trace(turn) - 1) / 2))) < 0.4  # from 1.5 (the tiny model's own: 0.26)
    assert aligned["psnr"] > stated["psnr"] + 2 and aligned["psnr"] > true["psnr"] - 0.5
    assert "aligned_poses" not in stated


def test_cli_resume_continues(scene_dir, tmp_path):
    out = tmp_path / "run"
    args = [str(scene_dir), "--out", str(out), "--points", "300", "--quiet", "--checkpoint-every", "5"]
    assert train_main(args + ["--iterations", "5"]) == 0
    killed = [temporary_path(out / name) for name in ("checkpoint.pt", "model.stg", "metrics.json")]
    for path in killed:  # what a kill during those writes leaves behind
        path.write_bytes(b"half")
    assert train_main(args + ["--iterations", "5", "--resume"]) == 0  # already done: exports again
    assert json.loads((out / "metrics.json").read_text())["iterations"] == 5
    assert not any(path.exists() for path in killed)


def test_cli_resume_of_a_broken_checkpoint_names_it(scene_dir, tmp_path, capsys):
    """--resume over a checkpoint.pt that is not one: exit 2, one line naming the file, nothing written."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"not a checkpoint")
    code = train_main([str(scene_dir), "--out", str(out), "--iterations", "2", "--quiet", "--resume"])
    err = capsys.readouterr().err
    assert code == 2
    assert f"{out / 'checkpoint.pt'}: not a readable checkpoint" in err and "--force" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt"]
    with pytest.raises(ValueError, match="checkpoint.pt: not a readable checkpoint"):
        Trainer.resume(load_n3v(scene_dir), out / "checkpoint.pt")


def _bad(tmp_path, scene_dir, what):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(scene_dir, bad, ignore=shutil.ignore_patterns(".stg_cache"))
    if what == "poses":
        (bad / "poses_bounds.npy").write_bytes(b"not a numpy file")
        return bad, bad / "poses_bounds.npy"
    if what == "missing_poses":
        (bad / "poses_bounds.npy").unlink()
        return bad, bad / "poses_bounds.npy"
    shutil.rmtree(bad / "frames")  # use the videos; make one unreadable
    (bad / "cam02.mp4").write_bytes(b"garbage")
    return bad, bad / "cam02.mp4"


@pytest.mark.parametrize("what", ["poses", "missing_poses", "video"])
def test_cli_bad_data_names_the_file(scene_dir, tmp_path, capsys, what):
    bad, culprit = _bad(tmp_path, scene_dir, what)
    code = train_main([str(bad), "--out", str(tmp_path / "out"), "--iterations", "2", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert str(culprit) in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_cli_usage_errors(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        train_main(["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    for option in ("--out", "--model", "--iterations", "--splatter", "--device", "--resume", "--checkpoint-every",
                   "--batch", "--seed", "--demo"):
        assert option in text
    assert train_main([str(tmp_path / "nowhere"), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "nowhere" in capsys.readouterr().err
    code = train_main([str(tmp_path), "--out", str(tmp_path / "o"), "--splatter", "gsplat", "--quiet"])
    assert code == 2 and "gsplat" in capsys.readouterr().err


def test_velocity_rates_follow_the_run_length(dataset):
    def rates(**cfg):
        trainer = Trainer(dataset, TrainConfig(num_points=100, depth_candidates=0, **cfg))
        return {g["name"]: g["lr"] for g in trainer.optimizer.param_groups}

    reference = rates(iterations=3000, stretch_rates=False)
    stretched = rates(iterations=3000)
    for name in ("motion", "omega"):
        assert stretched[name] == pytest.approx(10 * reference[name])  # 30000 / 3000
    assert {k: v for k, v in stretched.items() if k not in ("motion", "omega")} == \
        {k: v for k, v in reference.items() if k not in ("motion", "omega")}
    assert rates(iterations=30000)["motion"] == pytest.approx(reference["motion"])


def test_demo_scene_duration_keeps_a_longer_clips_frames(tmp_path):
    """ensure_demo_scene(duration=...) renders the first frames of a longer clip (its fader's timing),
    which bench/seams.py --offset relies on; without it, a shorter clip times its fader to itself."""
    import numpy as np

    from stg_train.pipeline import ensure_demo_scene
    sizes = dict(cameras=2, width=32, height=24)
    frames = lambda d: np.asarray(load_n3v(d, prefer_png=True).frames)  # noqa: E731
    long = frames(ensure_demo_scene(tmp_path / "long", frames=10, fps=4.0, **sizes))
    early = ensure_demo_scene(tmp_path / "early", frames=4, fps=4.0, duration=2.5, **sizes)
    alone = frames(ensure_demo_scene(tmp_path / "alone", frames=4, fps=4.0, **sizes))
    assert json.loads((early / "scene.json").read_text())["duration"] == 2.5
    assert np.array_equal(frames(early), long[:, :4])
    assert not np.array_equal(alone, long[:, :4])  # the fader is fully in at frame 2 of a 4-frame clip


def test_demo_scene_start_shows_the_same_clip_later_or_earlier(tmp_path):
    """ensure_demo_scene(start=...) renders the same scene from `start` seconds on (before its frame 0
    when negative), which bench/seams.py --offset relies on to put a video's end frame inside a
    segment."""
    import numpy as np

    from stg_train.pipeline import ensure_demo_scene
    sizes = dict(cameras=2, width=32, height=24, fps=4.0, duration=2.5)
    frames = lambda d: np.asarray(load_n3v(d, prefer_png=True).frames)  # noqa: E731
    long = frames(ensure_demo_scene(tmp_path / "long", frames=10, **sizes))
    later = ensure_demo_scene(tmp_path / "later", frames=4, start=1.0, **sizes)  # scene frames 4-7
    earlier = frames(ensure_demo_scene(tmp_path / "earlier", frames=8, start=-1.0, **sizes))  # -4 to 3
    assert json.loads((later / "scene.json").read_text())["start"] == 1.0
    assert np.array_equal(frames(later), long[:, 4:8])
    assert np.array_equal(earlier[:, 4:], long[:, :4])
    assert not np.array_equal(earlier[:, :4], long[:, :4])  # the sphere was elsewhere before frame 0
