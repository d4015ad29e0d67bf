"""Per-camera appearance and pose refinement (stg_train.rig.appearance, stg_train.rig.pose_refine): real training
on a tiny realistic capture undoes a known per-camera gain, the cameras' mean transform stays the
identity, the export holds the canonical scene and the refined cameras, an injected pose error is
recovered through the transform of the means, and checkpoints resume with both."""
from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_runtime.camera import Camera, load_camera_path  # noqa: E402
from stg_runtime.player import Player  # noqa: E402
from stg_train.rig.appearance import CameraAppearance  # noqa: E402
from stg_train.rig.capture import CameraEffects, CaptureModel, capture_record, pose_error, pose_errors  # noqa: E402
from stg_train.cli.synth import main as synth_main  # noqa: E402
from stg_train.data import load_n3v  # noqa: E402
from stg_train.export import export_trainer  # noqa: E402
from stg_train.rig.lens import known_falloff  # noqa: E402
from stg_train.params import Gaussians  # noqa: E402
from stg_train.rig.pose_refine import PoseCorrections  # noqa: E402
from stg_train.render import rasterize  # noqa: E402
from stg_train.synthetic import SyntheticScene, write_n3v  # noqa: E402
from stg_train.trainer import Trainer, TrainConfig  # noqa: E402

pytestmark = pytest.mark.usefixtures("two_torch_threads")

SCENE = dict(num_cameras=5, num_frames=6, fps=4.0, width=48, height=36)
#: Only a per-camera exposure (gain), so the truth is one number per camera.
GAIN_ONLY = CaptureModel(gain=0.3, white_balance=0, vignetting=0, noise=0, rotation_deg=0, translation=0, seed=1)
TRAIN = dict(iterations=250, num_points=1000, schedule={"refine_start": 30, "refine_every": 20, "reset_every": 0})


@pytest.fixture(scope="module")
def gain_capture(tmp_path_factory):
    path = tmp_path_factory.mktemp("gain_capture")
    write_n3v(path, SyntheticScene(seed=0, duration=SCENE["num_frames"] / SCENE["fps"]), capture=GAIN_ONLY, **SCENE)
    return path


@pytest.fixture(scope="module")
def trained(gain_capture):
    dataset = load_n3v(gain_capture, prefer_png=True)
    trainer = Trainer(dataset, TrainConfig(**TRAIN, appearance=True, appearance_vignetting=False))
    trainer.train(progress=False)
    return trainer


def test_appearance_undoes_a_known_per_camera_gain(trained, gain_capture):
    ds = trained.dataset
    gains = np.array([c["gain"] for c in capture_record(gain_capture)["cameras"]])[ds.train_cameras]
    truth = gains / gains.mean()  # the cameras' mean transform is the identity: gains relative to their mean
    learned = np.array([np.mean(np.diag(s["matrix"])) for s in trained.rig.appearance.summary()])
    before, after = np.abs(truth - 1).mean(), np.abs(truth - learned).mean()
    print(f"relative gains {truth.round(3)}, learned {learned.round(3)}: error {before:.3f} -> {after:.3f}")
    assert after < 0.5 * before
    assert np.all(np.sign(learned - 1) == np.sign(truth - 1))


def test_the_cameras_mean_transform_stays_the_identity(trained):
    summary = trained.rig.appearance.summary()
    np.testing.assert_allclose(np.mean([s["matrix"] for s in summary], axis=0), np.eye(3), atol=1e-5)
    np.testing.assert_allclose(np.mean([s["bias"] for s in summary], axis=0), 0.0, atol=1e-6)
    # and the transforms did move: the mean is held by the projection, not by standing still
    assert max(np.abs(np.asarray(s["matrix"]) - np.eye(3)).max() for s in summary) > 0.03


def test_the_export_renders_the_canonical_scene(trained, tmp_path):
    report = export_trainer(trained, tmp_path / "model.stg")  # checks the runtime against the trainer's render
    assert report.diff is not None and report.diff.ok
    player = Player(report.path, device="cpu")
    ds = trained.dataset
    cam = ds.cameras[ds.train_cameras[0]]
    canonical = trained.render_numpy(cam, 0.0)
    np.testing.assert_allclose(player.render(cam, 0.0), canonical, atol=2e-2)
    # the appearance is not in the file: the camera's transformed render differs from what the player draws
    with torch.no_grad():
        recorded = trained.rig.appearance.apply(torch.as_tensor(canonical), ds.train_cameras[0], cam).numpy()
    assert np.abs(recorded - canonical).mean() > 5e-3
    assert [c.name for c in player.cameras] == [c.name for c in ds.cameras]
    for a, b in zip(player.cameras, ds.cameras):  # no pose refinement: the stated cameras
        np.testing.assert_allclose(a.world_to_camera, b.world_to_camera, atol=1e-6)


def test_appearance_leaves_other_cameras_and_vignettes_around_the_principal_point():
    cam = Camera(40, 40, 16, 12, 32, 24, np.eye(4))
    appearance = CameraAppearance(3, [1, 2], "cpu", vignetting=True)
    image = torch.full((24, 32, 3), 0.5)
    assert appearance.apply(image, 0, cam) is image  # held out
    with torch.no_grad():
        appearance.falloff[1][0] = -0.3
    out = appearance.apply(image, 1, cam).detach().numpy()
    effects = CameraEffects(1.0, np.ones(3), 0.3, 0.0, np.zeros(3), np.zeros(3), 0)
    np.testing.assert_allclose(out, effects.apply(image.numpy(), cam), atol=1e-6)  # the capture's own model


def test_undo_inverts_the_transform_and_the_falloff():
    cam = Camera(40, 40, 16, 12, 32, 24, np.eye(4))
    appearance = CameraAppearance(3, [1, 2], "cpu", vignetting=True)
    with torch.no_grad():
        appearance.matrix[1].copy_(torch.tensor([[1.1, 0.05, 0.0], [0.0, 0.9, 0.02], [0.03, 0.0, 1.05]]))
        appearance.bias[1].copy_(torch.tensor([0.01, -0.02, 0.0]))
        appearance.falloff[1].copy_(torch.tensor([-0.3, 0.05]))
    recorded = torch.rand(24, 32, 3, generator=torch.Generator().manual_seed(0))
    canonical = appearance.undo(recorded, 1, cam)
    assert not torch.allclose(canonical, recorded, atol=0.01)
    torch.testing.assert_close(appearance.apply(canonical, 1, cam), recorded, atol=1e-5, rtol=1e-5)
    assert appearance.undo(recorded, 0, cam) is recorded  # held out


def test_guided_sampling_compares_the_pictures_as_the_canonical_scene_would_look(gain_capture):
    dataset = load_n3v(gain_capture, prefer_png=True)
    trainer = Trainer(dataset, TrainConfig(iterations=3, num_points=300, appearance=True, lens_falloff=(-0.3, 0.0)))
    ci = dataset.train_cameras[0]
    with torch.no_grad():
        trainer.rig.appearance.matrix[ci].mul_(1.2)
        trainer.rig.appearance.bias[ci].add_(0.02)
    canonical = trainer.canonical_truth(ci, 2)
    recorded = trainer.rig.appearance.apply(canonical, ci, dataset.cameras[ci]) * trainer.rig.falloff_map(ci)[..., None]
    torch.testing.assert_close(recorded, trainer.ground_truth(ci, 2), atol=1e-5, rtol=1e-5)
    assert (canonical - trainer.ground_truth(ci, 2)).abs().mean() > 0.02
    plain = Trainer(dataset, TrainConfig(iterations=3, num_points=300, appearance=False, lens_falloff=None))
    torch.testing.assert_close(plain.canonical_truth(ci, 2), plain.ground_truth(ci, 2), atol=0, rtol=0)


def _random_gaussians(n: int, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    means = torch.tensor(rng.uniform([-2, -1.5, 4], [2, 1.5, 7], (n, 3)), dtype=torch.float32)
    quats = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32), dim=-1)
    return Gaussians(means, quats, torch.full((n, 3), 0.05), torch.full((n,), 0.8),
                     torch.tensor(rng.uniform(size=(n, 3)), dtype=torch.float32))


def _render(g: Gaussians, camera: Camera):
    return rasterize(g.means, g.quats, g.scales, g.opacities, g.features, camera, backend="numba").features


def test_a_known_lens_falloff_keeps_the_vignetting_out_of_the_scene(tmp_path):
    vignetting = CaptureModel(gain=0, white_balance=0, vignetting=0.4, noise=0, rotation_deg=0, translation=0)
    scene = SyntheticScene(seed=0, duration=SCENE["num_frames"] / SCENE["fps"])
    write_n3v(tmp_path, scene, capture=vignetting, **SCENE)
    dataset = load_n3v(tmp_path, prefer_png=True)
    cam = dataset.cameras[dataset.test_cameras[0]]
    rim = np.zeros((cam.height, cam.width), bool)
    rim[:4], rim[-4:], rim[:, :4], rim[:, -4:] = True, True, True, True
    centre = np.zeros_like(rim)
    centre[12:24, 16:32] = True

    def rim_over_centre(config):  # the canonical render's brightness relative to the clean scene's
        trainer = Trainer(dataset, TrainConfig(**TRAIN, **config))
        trainer.train(progress=False)
        ratios = [trainer.render_numpy(cam, j / SCENE["num_frames"]).sum(-1) /
                  np.maximum(scene.render(cam, j / SCENE["fps"]).sum(-1), 0.05) for j in range(0, 6, 2)]
        return float(np.median([r[rim].mean() / r[centre].mean() for r in ratios]))

    known = rim_over_centre({"lens_falloff": (-0.4, 0.0)})
    learned_by_scene = rim_over_centre({"lens_falloff": None})
    print(f"rim / centre brightness against the clean scene: {known:.3f} with the falloff given, "
          f"{learned_by_scene:.3f} without")
    assert known > 0.93 and learned_by_scene < 0.88


def test_a_known_falloff_out_of_range_is_refused_before_training(tmp_path):
    assert known_falloff((-0.3,)) == (-0.3, 0.0) and known_falloff([-0.3, 0.05]) == (-0.3, 0.05)
    for bad, says in (((-1.0,), "0 .. 1"), ((0.5, 0.6), "1 .. 2.1"), ((float("nan"),), "finite"), ((), "K1")):
        with pytest.raises(ValueError, match=says.replace(".", r"\.")):
            known_falloff(bad)
    write_n3v(tmp_path, SyntheticScene(seed=0, duration=SCENE["num_frames"] / SCENE["fps"]), **SCENE)
    with pytest.raises(ValueError, match="must stay within"):
        Trainer(load_n3v(tmp_path, prefer_png=True), TrainConfig(**TRAIN, lens_falloff=(-1.5, 0.0)))


def test_the_transform_of_the_means_renders_the_corrected_camera():
    g = _random_gaussians(2000)
    stated = Camera(57.6, 57.6, 32, 24, 64, 48, np.eye(4), name="c")
    poses = PoseCorrections([0], [stated], "cpu")
    with torch.no_grad():
        poses.rotation[0].copy_(torch.tensor([0.01, -0.02, 0.015]))
        poses.translation[0].copy_(torch.tensor([0.03, 0.01, -0.02]))
    mapped, _ = poses.apply(g, torch.zeros(48, 64, 6), 0, stated)
    refined = poses.refined([stated])[0]
    np.testing.assert_allclose(_render(mapped, stated).detach().numpy(), _render(g, refined).detach().numpy(),
                               atol=2e-3)


def test_pose_refinement_recovers_an_injected_pose_error():
    g = _random_gaussians(3000)
    true = Camera(57.6, 57.6, 32, 24, 64, 48, np.eye(4), name="c")
    error = CameraEffects(1.0, np.ones(3), 0, 0, np.radians(1.0) * np.array([0.6, 0.8, 0.0]),
                          np.array([0.03, -0.02, 0.01]), 0)
    stated = error.perturb(true)
    target = _render(g, true).detach()
    poses = PoseCorrections([0], [stated], "cpu")
    optimizer = torch.optim.Adam(poses.param_groups({"rotation": 1e-3, "translation": 1e-3}), eps=1e-15)
    rays = torch.zeros(48, 64, 6)
    for _ in range(150):
        mapped, _ = poses.apply(g, rays, 0, stated)
        (_render(mapped, stated) - target).abs().mean().backward()
        optimizer.step()
        optimizer.zero_grad()
    before, after = pose_error(stated, true.world_to_camera), pose_error(poses.refined([stated])[0], true.world_to_camera)
    print(f"pose error {before[0]:.3f} deg {before[1]:.4f} -> {after[0]:.3f} deg {after[1]:.4f}")
    assert after[0] < 0.2 * before[0] and after[1] < 0.2 * before[1]


def test_the_view_inputs_follow_the_refined_camera():
    stated = Camera(57.6, 57.6, 32, 24, 64, 48, np.eye(4), name="c")
    poses = PoseCorrections([0], [stated], "cpu")
    with torch.no_grad():
        poses.rotation[0].copy_(torch.tensor([0.02, 0.01, -0.03]))
        poses.translation[0].copy_(torch.tensor([0.1, -0.05, 0.02]))
    from stg_train.params import view_inputs

    _, rays = poses.apply(_random_gaussians(10), view_inputs(stated, "cpu"), 0, stated)
    expected = view_inputs(poses.refined([stated])[0], "cpu")
    np.testing.assert_allclose(rays.detach().numpy(), expected.numpy(), atol=1e-5)


def test_pose_errors_against_the_capture_record(tmp_path):
    model = CaptureModel(rotation_deg=0.5, translation=0.02, seed=2)
    write_n3v(tmp_path, SyntheticScene(seed=0, duration=1.0), num_cameras=3, num_frames=1, fps=1, width=32,
              height=24, capture=model)
    ds = load_n3v(tmp_path, prefer_png=True)
    errors = pose_errors(ds.cameras, capture_record(tmp_path))
    assert errors["rotation_deg"] == pytest.approx(0.5, abs=1e-3)  # the LLFF file's float64 round trip
    assert errors["translation"] == pytest.approx(0.02, abs=1e-5)


class _Killed(Exception):
    pass


def test_checkpoints_resume_with_appearance_and_pose_refinement(gain_capture, tmp_path):
    dataset = load_n3v(gain_capture, prefer_png=True)
    cfg = dict(iterations=16, num_points=300, checkpoint_every=8, appearance=True, pose_refine=True,
               schedule={"refine_start": 8, "refine_every": 4, "densify_rounds": 1, "reset_every": 0})
    straight = Trainer(dataset, TrainConfig(**cfg), out_dir=tmp_path / "a")
    straight.train(progress=False)

    def kill(trainer):
        if trainer.step == 11:
            raise _Killed

    run = Trainer(dataset, TrainConfig(**cfg), out_dir=tmp_path / "b")
    with pytest.raises(_Killed):
        run.train(progress=False, callback=kill)
    resumed = Trainer.resume(dataset, tmp_path / "b" / "checkpoint.pt")
    assert resumed.step == 8 and resumed.rig.appearance is not None and resumed.rig.poses is not None
    resumed.train(progress=False)
    for key in ("matrix", "bias", "falloff"):
        assert torch.equal(straight.rig.appearance.state_dict()[key], resumed.rig.appearance.state_dict()[key])
    for key in ("rotation", "translation"):
        a, b = straight.rig.poses.state_dict()[key], resumed.rig.poses.state_dict()[key]
        assert torch.equal(a, b) and a.abs().max() > 0
    sa, sb = straight.rig.optimizer.state_dict(), resumed.rig.optimizer.state_dict()
    for k in sa["state"]:
        assert torch.equal(sa["state"][k]["exp_avg"], sb["state"][k]["exp_avg"])
    # the exported file stores the refined training cameras and the held-out camera as stated
    player = Player(export_trainer(resumed, tmp_path / "model.stg").path, device="cpu")
    refined = resumed.refined_cameras()
    for i, cam in enumerate(player.cameras):
        np.testing.assert_allclose(cam.world_to_camera, refined[i].world_to_camera, atol=1e-6)
    held = dataset.test_cameras[0]
    np.testing.assert_allclose(player.cameras[held].world_to_camera, dataset.cameras[held].world_to_camera, atol=1e-9)
    moved = dataset.train_cameras[0]
    assert np.abs(player.cameras[moved].world_to_camera - dataset.cameras[moved].world_to_camera).max() > 1e-7


def test_stg_synth_realistic_writes_the_capture_it_was_asked_for(tmp_path, capsys):
    out = tmp_path / "scene"
    assert synth_main([str(out), "--cameras", "2", "--frames", "1", "--size", "16x12", "--quiet", "--gain", "0",
                       "--noise", "0.02", "--pose-rotation", "0.4", "--seed", "3"]) == 0
    record = json.loads((out / "scene.json").read_text())["capture"]
    assert record["gain"] == 0 and record["noise"] == 0.02 and record["rotation_deg"] == 0.4 and record["seed"] == 3
    assert record["vignetting"] == CaptureModel().vignetting  # a knob left out keeps its default
    assert [c["gain"] for c in record["cameras"]] == [1.0, 1.0]
    assert synth_main([str(tmp_path / "clean"), "--cameras", "2", "--frames", "1", "--size", "16x12", "--quiet"]) == 0
    assert "capture" not in json.loads((tmp_path / "clean" / "scene.json").read_text())
    with pytest.raises(SystemExit) as e:
        synth_main([str(tmp_path / "x"), "--vignetting", "-0.1"])
    assert e.value.code == 2


def test_stg_train_writes_the_refined_cameras_and_stg_eval_takes_them(gain_capture, tmp_path, capsys):
    from stg_train.cli.eval import main as eval_main
    from stg_train.cli.train import main as train_main

    out = tmp_path / "run"
    assert train_main([str(gain_capture), "--out", str(out), "--iterations", "6", "--points", "300", "--appearance",
                       "--pose-refine", "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["settings"]["appearance"] and metrics["settings"]["pose_refine"]
    assert metrics["pose_error"]["stated"]["rotation_deg"] == pytest.approx(0.0, abs=1e-3)  # GAIN_ONLY: exact poses
    refined = load_camera_path(out / "refined_cameras.json")
    stored = Player(out / "model.stg", device="cpu").cameras
    for a, b in zip(refined, stored):
        assert a.name == b.name
        np.testing.assert_allclose(a.world_to_camera, b.world_to_camera, atol=1e-6)
    capsys.readouterr()
    assert eval_main([str(out / "model.stg"), str(gain_capture), "--no-lpips"]) == 0  # the refined cameras pass
    assert "psnr" in capsys.readouterr().out.lower()
