"""The rig measured from its own pictures before training (stg_train.rig.self_calibration): its lenses'
falloff, its cameras' colour gains and their stated poses against the epipolar lines, on synthetic
captures whose truth is known (stg_train.rig.capture), and what training decides from it ("auto")."""
import copy
import json
from dataclasses import asdict, replace

import numpy as np
import pytest
import torch

from stg_train.rig.capture import CaptureModel, with_vignetting
from stg_train.config import TrainConfig
from stg_train.data import load_n3v
from stg_train.data.dataset import Dataset
from stg_train.rotations import rotation_from_axis_angle
from stg_train.rig.self_calibration import (EPIPOLAR, GAIN_SPREAD, _epipolar_distances, _Match, calibrate_rig,
                                        measure_rig_with_depth, measure_rig)
from stg_train.synthetic import SyntheticScene, write_n3v
from stg_train.trainer import Trainer


def _capture(folder, capture):
    effects = write_n3v(folder, SyntheticScene(seed=0, duration=1.0), num_frames=2, capture=capture)
    return load_n3v(folder, prefer_png=True), effects


@pytest.fixture(scope="module")
def realistic(tmp_path_factory):
    """The default realistic capture (exposure, white balance, vignetting 0.3, noise, pose error), 2 frames."""
    folder = tmp_path_factory.mktemp("realistic")
    dataset, _ = _capture(folder, CaptureModel(seed=0))
    return dataset, CaptureModel(seed=0).draw(12, held_out=[0])  # as write_n3v draws it


def test_a_shared_falloff_and_the_cameras_gains_are_measured(realistic):
    dataset, effects = realistic
    estimate = measure_rig(dataset)
    assert abs(estimate.corner_brightness - 0.7) < 0.04, estimate  # truth: 30 % darker at the corners
    truth = np.array([effects[c].gain * effects[c].white_balance for c in dataset.train_cameras])
    truth /= truth.mean(0)
    found = estimate.gains / estimate.gains.mean(0)
    assert np.abs(found / truth - 1).mean() < 0.25 * np.abs(1 / truth - 1).mean()
    assert estimate.pairs > 10_000 and estimate.frames == (0, 1)


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """The same scene captured cleanly, 2 frames."""
    return _capture(tmp_path_factory.mktemp("clean"), None)[0]


def test_a_clean_capture_measures_no_falloff(clean):
    estimate = measure_rig(clean)
    assert abs(estimate.corner_brightness - 1.0) < 0.04
    assert np.abs(estimate.camera_corners - 1.0).max() < 0.05  # each camera's own fit too
    assert estimate.gain_spread < GAIN_SPREAD / 3


def test_auto_decides_nothing_to_correct_on_a_clean_capture(clean):
    config, calibration = calibrate_rig(clean, TrainConfig())
    assert (config.lens_falloff, config.appearance, config.pose_refine) == (None, False, False)  # as before "auto"
    assert calibration.lens_falloff is None and calibration.estimate.epipolar < EPIPOLAR / 1.5
    assert "training without one" in calibration.notes[0] and "no per-camera appearance" in calibration.notes[1]
    assert "not refined" in calibration.notes[2]


def test_auto_trains_a_clean_capture_to_the_same_bits_as_neither(clean):
    def trained(**settings):
        trainer = Trainer(clean, TrainConfig(iterations=4, num_points=300, **settings))
        trainer.train(progress=False)
        state = trainer.params.state_dict()
        return {**state["raw"], **{f"decoder.{k}": v for k, v in state["decoder"].items()}}

    auto = trained()  # the measurement draws no random number
    neither = trained(lens_falloff=None, appearance=False, pose_refine=False)
    assert auto.keys() == neither.keys() and all(torch.equal(auto[k], neither[k]) for k in auto)


def test_auto_decides_a_falloff_and_an_appearance_on_a_realistic_capture(realistic):
    dataset, _ = realistic
    config, calibration = calibrate_rig(dataset, TrainConfig(model="lite"))
    assert config.lens_falloff == calibration.estimate.k and abs(calibration.estimate.corner_brightness - 0.7) < 0.04
    assert config.appearance is True and calibration.estimate.gain_spread > 2 * GAIN_SPREAD
    assert config.pose_refine is True and calibration.estimate.epipolar > 1.2 * EPIPOLAR  # 0.15 degrees off
    assert "refining them" in calibration.notes[2]
    assert config.model == "lite"  # the rest is untouched
    given, _ = calibrate_rig(dataset, TrainConfig(lens_falloff=(-0.3, 0.0), appearance=False, pose_refine=False))
    assert (given.lens_falloff, given.appearance, given.pose_refine) == ((-0.3, 0.0), False, False)  # as given


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_the_epipolar_distance_is_zero_for_true_matches_and_grows_with_a_pose_error(model):
    a, b = SyntheticScene().dome_cameras(2, 160, 120, hfov_deg=100.0, model=model)
    v, u = np.mgrid[0:120, 0:160].astype(np.float64)
    points = a.unproject(u + 0.5, v + 0.5, 3.0 + 0.5 * np.sin(u / 9.0))  # a wavy surface in front of a
    uv, z = b.project(points.reshape(-1, 3))
    match = _Match((uv[:, 0] - 0.5).reshape(120, 160).astype(np.float32),
                   (uv[:, 1] - 0.5).reshape(120, 160).astype(np.float32),
                   (z > 0).reshape(120, 160), np.ones((120, 160), np.float32))  # the true matches
    exact = _epipolar_distances(a, b, match)
    assert len(exact) > 10_000 and np.median(exact) < 1e-3
    w2c = b.world_to_camera.copy()
    w2c[:3, :3] = rotation_from_axis_angle(np.radians([0.15, 0.0, 0.0])) @ w2c[:3, :3]  # stated 0.15 degrees off
    off = np.median(_epipolar_distances(a, replace(b, world_to_camera=w2c), match))
    assert 0.03 < off < 0.3, off  # at most 0.15 degrees x the focal length (0.25 px), along the lines' normal


def test_lenses_that_differ_are_told_apart_and_no_shared_falloff_is_trained(clean):
    mixed = with_vignetting(clean, [c for c in clean.train_cameras if c % 2])  # every other lens vignettes 30 %
    estimate = measure_rig(mixed)
    corners = dict(zip(mixed.train_cameras, estimate.camera_corners))
    assert all(abs(corners[c] - (0.7 if c % 2 else 1.0)) < 0.05 for c in corners), corners
    config, calibration = calibrate_rig(mixed, TrainConfig())
    assert config.lens_falloff is None and "not one lens" in calibration.notes[0]
    assert config.appearance is True and "their lenses differ" in calibration.notes[1]  # each learns its own


def test_a_rig_that_cannot_be_measured_trains_with_none_of_the_three():
    cams = SyntheticScene().cameras(4, 64, 48)
    dark = Dataset(cams, np.zeros((4, 1, 48, 64, 3), np.uint8), 30.0, test_cameras=[0])
    config, calibration = calibrate_rig(dark, TrainConfig())
    assert (config.lens_falloff, config.appearance, config.pose_refine) == (None, False, False)
    assert calibration.estimate is None
    assert "not measured (the training cameras overlap too little" in calibration.notes[0]
    assert "camera poses: not checked (the training cameras overlap too little" in calibration.notes[2]


def test_pictures_with_nothing_to_match_are_refused():
    cams = SyntheticScene().cameras(4, 64, 48)
    dark = Dataset(cams, np.zeros((4, 1, 48, 64, 3), np.uint8), 30.0, test_cameras=[0])
    with pytest.raises(ValueError, match="overlap too little"):
        measure_rig(dark)
    with pytest.raises(ValueError, match="two or more training cameras"):
        measure_rig(Dataset(cams[:2], np.zeros((2, 1, 48, 64, 3), np.uint8), 30.0, test_cameras=[0]))


def test_the_trainer_measures_auto_and_trains_with_the_numbers(realistic):
    dataset, _ = realistic
    trainer = Trainer(dataset, TrainConfig(iterations=1, num_points=500))  # the defaults: "auto"
    assert trainer.rig.calibration is not None
    assert trainer.config.lens_falloff == trainer.rig.calibration.estimate.k == trainer.rig.lens_falloff
    assert trainer.config.appearance is True and trainer.rig.appearance is not None
    assert trainer.config.pose_refine is True and trainer.rig.poses is not None
    assert not trainer.rig.appearance.vignetting  # the falloff is known now: the cameras learn none


def test_stg_train_says_what_it_measured_and_a_resumed_run_keeps_it(realistic, tmp_path, capsys):
    from stg_train.pipeline import train

    dataset, _ = realistic
    config = TrainConfig(iterations=2, num_points=500)
    first = train(dataset, tmp_path, config)
    said = capsys.readouterr().err
    assert "lens falloff measured from the cameras' overlap: K1" in said and "training with it" in said
    assert "learning a per-camera appearance" in said
    k = first["settings"]["lens_falloff"]
    assert len(k) == 2 and -0.4 < k[0] < -0.2  # numbers, not "auto": what the checkpoint and metrics keep
    assert first["settings"]["appearance"] is True
    again = train(dataset, tmp_path, TrainConfig(iterations=3, num_points=500), resume=True,
                  given={"lens_falloff": "--lens-falloff auto", "iterations": "--iterations 3"})
    assert again["settings"]["lens_falloff"] == k and again["settings"]["appearance"] is True
    assert again["iterations"] == 3
    assert "lens falloff measured" not in capsys.readouterr().err  # not measured again


def test_checkpoints_saved_before_auto_resume_without_either():
    old = {k: v for k, v in asdict(TrainConfig()).items() if k not in ("appearance", "lens_falloff", "pose_refine")}
    config = TrainConfig.from_dict(old)
    assert (config.appearance, config.lens_falloff, config.pose_refine) == (False, None, False)


def test_segments_share_one_measurement_of_the_whole_video(tmp_path, capsys):
    from stg_train.pipeline import train

    dataset, _ = _capture(tmp_path / "data", CaptureModel(seed=0))
    metrics = train(dataset, tmp_path / "out", TrainConfig(iterations=2, num_points=500), segment_frames=1)
    said = capsys.readouterr().err
    assert said.count("lens falloff measured from the cameras' overlap") == 1  # once, not per segment
    assert "at frames 0, 1" in said  # the whole video's frames
    segment = [json.loads((tmp_path / "out" / "segments" / f"{i:02d}" / "metrics.json").read_text()) for i in range(2)]
    chosen = {tuple(m["settings"]["lens_falloff"]) for m in segment}
    assert len(chosen) == 1 and metrics["settings"]["appearance"] is True
    gains = [m["settings"]["camera_gains"] for m in segment]  # the initial points' too
    assert gains[0] == gains[1] and sorted(gains[0]) == [dataset.cameras[c].name for c in dataset.train_cameras]


def test_stg_train_leaves_both_auto_unless_told():
    from stg_train.cli.train import _config, build_parser

    def config(*options):
        return _config(build_parser().parse_args(["data", "--out", "out", *options]), "numba")

    assert (config().lens_falloff, config().appearance, config().pose_refine) == ("auto", "auto", "auto")
    told = config("--lens-falloff", "none", "--no-appearance", "--no-pose-refine")
    assert (told.lens_falloff, told.appearance, told.pose_refine) == (None, False, False)
    told = config("--lens-falloff=-0.2", "--appearance", "--pose-refine")
    assert (told.lens_falloff, told.appearance, told.pose_refine) == ((-0.2, 0.0), True, True)


@pytest.fixture(scope="module")
def vignetting_only(tmp_path_factory):
    """The scene captured with the default vignetting (30 % at the corners) and nothing else, 2 frames."""
    capture = CaptureModel(gain=0, white_balance=0, noise=0, rotation_deg=0, translation=0)
    return _capture(tmp_path_factory.mktemp("vignetting"), capture)[0]


def _true_depths(dataset):
    """{(camera, frame): (depth, alpha)} of the scene's true geometry, as a perfect model renders it."""
    scene = SyntheticScene(seed=0, duration=1.0)
    depths = {}
    for c in dataset.train_cameras:
        for f in range(dataset.num_frames):
            depth = scene.render(dataset.cameras[c], f / dataset.fps, return_depth=True)[1]
            depths[c, f] = (depth, np.ones_like(depth))
    return depths


def test_the_models_geometry_measures_the_falloff_without_the_flows_bias(vignetting_only, clean):
    flow = measure_rig(vignetting_only)
    found = measure_rig_with_depth(vignetting_only, vignetting_only.cameras, _true_depths(vignetting_only), (0, 1))
    assert abs(found.corner_brightness - 0.7) < 0.01 and found.corner_error < 0.01 and found.pairs > 10_000
    assert abs(found.corner_brightness - 0.7) < abs(flow.corner_brightness - 0.7)
    none = measure_rig_with_depth(clean, clean.cameras, _true_depths(clean), (0, 1))
    assert abs(none.corner_brightness - 1.0) < 0.01
    # large pictures are measured scaled down, as the flow's are: here to 80 x 60
    small = measure_rig_with_depth(vignetting_only, vignetting_only.cameras, _true_depths(vignetting_only), (0, 1),
                                   max_side=80)
    assert abs(small.corner_brightness - 0.7) < 0.02 and small.pairs < found.pairs / 3


def test_a_geometry_that_matches_nothing_is_refused(clean):
    depths = {key: (depth, np.zeros_like(alpha)) for key, (depth, alpha) in _true_depths(clean).items()}  # transparent
    with pytest.raises(ValueError, match="matches too few pixels"):
        measure_rig_with_depth(clean, clean.cameras, depths, (0, 1))


def test_the_trainer_measures_the_falloff_again_a_third_of_the_way(vignetting_only, tmp_path, monkeypatch):
    import stg_train.rig.remeasure as remeasure_module

    seen = {}
    def geometry(dataset, cameras, depths, frames):  # the model's geometry after 2 steps is not the scene's yet
        seen.update(step=trainer.step, frames=frames, cameras=len(depths))
        return measure_rig_with_depth(dataset, cameras, _true_depths(dataset), frames)

    monkeypatch.setattr(remeasure_module, "measure_rig_with_depth", geometry)
    trainer = Trainer(vignetting_only, TrainConfig(iterations=6, num_points=500), out_dir=tmp_path)
    flow_k = trainer.rig.lens_falloff
    trainer.train(progress=False)
    assert seen == {"step": 2, "frames": (0, 1), "cameras": 2 * 11}
    assert trainer.config.lens_falloff == trainer.rig.lens_falloff != flow_k
    assert abs(1 + sum(trainer.rig.lens_falloff) - 0.7) < 0.01
    assert trainer.rig.remeasure_note.startswith("the rig measured again at step 2, from the model's geometry: lens falloff K1")
    assert trainer.rig.remeasure == {"falloff": True, "gains": False}  # no appearance learned: the colours agree
    resumed = Trainer.resume(vignetting_only, tmp_path / "checkpoint.pt")
    assert resumed.rig.lens_falloff == trainer.rig.lens_falloff and resumed.rig.remeasure == trainer.rig.remeasure
    seen.clear()
    given = Trainer(vignetting_only, TrainConfig(iterations=3, num_points=500, lens_falloff=(-0.3, 0.0)))
    given.train(progress=False)
    assert not any(given.rig.remeasure.values()) and given.rig.remeasure_note is None and seen == {}  # a known falloff stays


def test_a_measurement_again_that_disagrees_keeps_the_flows(vignetting_only, monkeypatch):
    import stg_train.rig.remeasure as remeasure_module
    from stg_train.rig.self_calibration import GeometricMeasurement

    monkeypatch.setattr(remeasure_module, "measure_rig_with_depth",
                        lambda *args: GeometricMeasurement((-0.6, 0.0), 0.001, 50_000, np.ones((11, 3))))  # far from the flow's
    trainer = Trainer(vignetting_only, TrainConfig(iterations=3, num_points=500))
    flow_k = trainer.rig.lens_falloff
    trainer.train(progress=False)
    assert trainer.rig.lens_falloff == flow_k == trainer.config.lens_falloff
    assert "disagrees with the flow's" in trainer.rig.remeasure_note


def _true_cameras(dataset):
    """The dataset's cameras at the true poses its capture record keeps (stg_train.rig.capture)."""
    from stg_train.rig.capture import capture_record

    truth = {c["name"]: np.asarray(c["true_world_to_camera"]) for c in capture_record(dataset.path)["cameras"]}
    return [replace(c, world_to_camera=truth[c.name]) for c in dataset.cameras]


def test_the_models_geometry_measures_the_cameras_gains(realistic):
    dataset, effects = realistic
    cameras = _true_cameras(dataset)
    truth = np.log([effects[c].gain * effects[c].white_balance for c in dataset.train_cameras])
    truth -= truth.mean(0)
    found = measure_rig_with_depth(dataset, cameras, _true_depths(replace_cameras(dataset, cameras)), (0, 1))
    flow = measure_rig(dataset)
    error = lambda gains: np.sqrt(np.mean((np.log(gains) - np.log(gains).mean(0) - truth) ** 2))
    assert error(found.gains) < 0.1 * np.sqrt(np.mean(truth ** 2))  # within a tenth of the cameras' spread
    assert error(found.gains) < 0.5 * error(flow.gains)
    assert abs(found.corner_brightness - 0.7) < 0.015


def replace_cameras(dataset, cameras):
    view = copy.copy(dataset)
    view.cameras = list(cameras)
    return view


def test_the_appearance_is_set_from_the_measured_gains_and_held(realistic, monkeypatch):
    import stg_train.rig.remeasure as remeasure_module
    from stg_train.rig.self_calibration import GeometricMeasurement

    dataset, _ = realistic
    taken = {}
    def measured(ds, cameras, depths, frames):  # the gains learned so far, each within 2 %
        learned = np.array([np.diag(a["matrix"]) for a in trainer.rig.appearance.summary()])
        taken["gains"] = learned * np.exp(np.random.default_rng(1).uniform(-0.02, 0.02, learned.shape))
        return GeometricMeasurement((-0.29, -0.01), 0.001, 50_000, taken["gains"])

    monkeypatch.setattr(remeasure_module, "measure_rig_with_depth", measured)
    trainer = Trainer(dataset, TrainConfig(iterations=6, num_points=500))
    assert trainer.rig.appearance is not None and abs(1 + sum(trainer.rig.lens_falloff) - 0.7) < 0.04
    trainer.train(progress=False)
    expected = taken["gains"] / taken["gains"].mean(0)
    for c, row in zip(dataset.train_cameras, expected):
        np.testing.assert_allclose(trainer.rig.appearance.matrix[c].detach().numpy(), np.diag(row), atol=1e-6)  # held
        assert not trainer.rig.appearance.bias[c].detach().abs().any()
    assert trainer.rig.lens_falloff == (-0.29, -0.01)
    assert trainer.rig.remeasure == {"falloff": True, "gains": True}
    assert "lens falloff K1 -0.290" in trainer.rig.remeasure_note
    assert "the cameras' colours set from it and held" in trainer.rig.remeasure_note


def test_colours_without_a_falloff_are_measured_again_and_held(tmp_path, monkeypatch):
    import stg_train.rig.remeasure as remeasure_module
    from stg_train.rig.self_calibration import GeometricMeasurement

    capture = CaptureModel(vignetting=0, noise=0, rotation_deg=0, translation=0)  # exposure and white balance alone
    dataset, _ = _capture(tmp_path / "data", capture)
    trainer = Trainer(dataset, TrainConfig(iterations=6, num_points=500))
    assert trainer.rig.lens_falloff is None and trainer.rig.appearance is not None  # no falloff measured, colours learned
    assert trainer.rig.remeasure == {"falloff": False, "gains": True}
    learned = {}
    def measured(ds, cameras, depths, frames):  # the gains the appearance has learned, 2 % off for one camera
        gains = np.array([np.diag(a["matrix"]) for a in trainer.rig.appearance.summary()])
        gains[0] *= 1.02
        learned["gains"] = gains
        return GeometricMeasurement((0.0, 0.0), 0.001, 50_000, gains)

    monkeypatch.setattr(remeasure_module, "measure_rig_with_depth", measured)
    trainer.train(progress=False)
    expected = learned["gains"] / learned["gains"].mean(0)
    for c, row in zip(dataset.train_cameras, expected):
        np.testing.assert_allclose(np.diag(trainer.rig.appearance.matrix[c].detach().numpy()), row, atol=1e-6)
    assert trainer.rig.lens_falloff is None and "colours set from it and held" in trainer.rig.remeasure_note
    # gains far from what was learned (a model whose geometry is not the scene's) are not taken
    monkeypatch.setattr(remeasure_module, "measure_rig_with_depth",
                        lambda *args: GeometricMeasurement((0.0, 0.0), 0.001, 50_000, np.exp(np.eye(11, 3))))
    other = Trainer(dataset, TrainConfig(iterations=6, num_points=500))
    other.train(progress=False)
    assert "differ from the ones learned" in other.rig.remeasure_note and other.rig.optimizer.param_groups[0]["lr"] > 0


def _on_the_surface(dataset, cameras, points, tolerance: float = 0.02) -> float:
    """The share of initial points within `tolerance` (relative depth) of the surface that one of
    `cameras` (true poses) sees through the pixel the point falls in, at the point's frame."""
    scene = SyntheticScene(seed=0, duration=1.0)
    frames = np.round(points.t_center * dataset.num_frames).astype(int)
    best = np.full(len(points.xyz), np.inf)
    for j in np.unique(frames):
        at = frames == j
        for c in dataset.train_cameras:
            camera = cameras[c]
            true_depth = scene.render(camera, j / dataset.fps, return_depth=True)[1]
            uv, z = camera.project(points.xyz[at])
            inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
            u, v = uv[inside].astype(int).T
            error = np.full(at.sum(), np.inf)
            error[inside] = np.abs(z[inside] / true_depth[v, u] - 1)
            best[at] = np.minimum(best[at], error)
    return float((best < tolerance).mean())


def test_the_initial_points_match_the_pictures_as_the_canonical_scene_would_look(realistic, clean):
    from stg_train.data.points import initial_points
    from stg_train.rig.lens import lens_brightness

    dataset, _ = realistic
    trainer = Trainer(dataset, TrainConfig(iterations=3, num_points=500))
    brightness = trainer.rig.initial_brightness()  # the falloff trained with, times the gains measured
    gains = trainer.rig.calibration.estimate.gains
    assert trainer.config.camera_gains == {dataset.cameras[c].name: tuple(gains[n])
                                           for n, c in enumerate(dataset.train_cameras)}
    assert sorted(brightness) == dataset.train_cameras
    for n, c in enumerate(dataset.train_cameras):
        camera = dataset.cameras[c]
        np.testing.assert_allclose(brightness[c][int(camera.cy), int(camera.cx)], gains[n], rtol=0.01)
        np.testing.assert_allclose(brightness[c][0, 0], lens_brightness(1.0, trainer.rig.lens_falloff) * gains[n], rtol=0.02)
    corrected = dataset.corrected(brightness)
    drawn = initial_points(corrected, "volume", 500, np.random.default_rng(0), depth_candidates=64)
    np.testing.assert_array_equal(trainer.initial.xyz, drawn.xyz)  # the trainer's are drawn from these pictures
    np.testing.assert_array_equal(trainer.initial.rgb, drawn.rgb)
    c = dataset.train_cameras[0]
    np.testing.assert_array_equal(corrected.frame(c, 1), dataset.frame(c, 1))  # the pictures trained on stay
    np.testing.assert_allclose(corrected.image(c, 1), np.clip(dataset.image(c, 1) / brightness[c], 0, 1))
    np.testing.assert_array_equal(corrected.image(0, 1), dataset.image(0, 1))  # the held-out camera, as it is
    # the view volume's depth search: cameras that disagree in colour and vignette pick wrong depths
    as_captured = initial_points(dataset, "volume", 3000, np.random.default_rng(0), depth_candidates=64)
    as_canonical = initial_points(corrected, "volume", 3000, np.random.default_rng(0), depth_candidates=64)
    truth = _true_cameras(dataset)
    before, after = _on_the_surface(dataset, truth, as_captured), _on_the_surface(dataset, truth, as_canonical)
    reference = _on_the_surface(clean, clean.cameras, initial_points(clean, "volume", 3000, np.random.default_rng(0),
                                                                      depth_candidates=64))
    assert after > before + 0.15 and after > reference - 0.15, (before, after, reference)
    plain = Trainer(clean, TrainConfig(iterations=3, num_points=500))
    assert plain.rig.initial_brightness() == {} and plain.config.camera_gains is None  # nothing to correct
