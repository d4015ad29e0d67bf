"""The rig's lens falloff measured from its own pictures (stg_train.self_calibration), on synthetic
captures whose falloff and colour gains are known (stg_train.capture)."""
import numpy as np
import pytest

from stg_train.capture import CaptureModel
from stg_train.config import TrainConfig
from stg_train.data import load_n3v
from stg_train.data.dataset import Dataset
from stg_train.self_calibration import estimate_lens_falloff
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
    return dataset, CaptureModel(seed=0).draw(12)


def test_a_shared_falloff_and_the_cameras_gains_are_measured(realistic):
    dataset, effects = realistic
    estimate = estimate_lens_falloff(dataset)
    assert abs(estimate.corner_brightness - 0.7) < 0.04, estimate  # truth: 30 % darker at the corners
    truth = np.array([effects[c].gain * effects[c].white_balance for c in dataset.train_cameras])
    truth /= truth.mean(0)
    found = estimate.gains / estimate.gains.mean(0)
    assert np.abs(found / truth - 1).mean() < 0.25 * np.abs(1 / truth - 1).mean()
    assert estimate.pairs > 10_000 and estimate.frames == (0, 1)


def test_a_clean_capture_measures_no_falloff(tmp_path):
    dataset, _ = _capture(tmp_path, None)
    assert abs(estimate_lens_falloff(dataset).corner_brightness - 1.0) < 0.04


def test_pictures_with_nothing_to_match_are_refused():
    cams = SyntheticScene().cameras(4, 64, 48)
    dark = Dataset(cams, np.zeros((4, 1, 48, 64, 3), np.uint8), 30.0, test_cameras=[0])
    with pytest.raises(ValueError, match="overlap too little"):
        estimate_lens_falloff(dark)
    with pytest.raises(ValueError, match="two or more training cameras"):
        estimate_lens_falloff(Dataset(cams[:2], np.zeros((2, 1, 48, 64, 3), np.uint8), 30.0, test_cameras=[0]))


def test_the_trainer_measures_auto_and_trains_with_the_numbers(realistic):
    dataset, _ = realistic
    trainer = Trainer(dataset, TrainConfig(lens_falloff="auto", appearance=True, iterations=1, num_points=500))
    assert trainer.falloff_estimate is not None
    assert trainer.config.lens_falloff == trainer.falloff_estimate.k == trainer.lens_falloff
    assert not trainer.appearance.vignetting  # the falloff is known now: the cameras learn none


def test_stg_train_says_what_it_measured_and_a_resumed_run_keeps_it(realistic, tmp_path, capsys):
    from stg_train.pipeline import train

    dataset, _ = realistic
    config = TrainConfig(lens_falloff="auto", iterations=2, num_points=500)
    first = train(dataset, tmp_path, config)
    said = capsys.readouterr().err
    assert "lens falloff measured from the cameras' overlap: K1" in said
    k = first["settings"]["lens_falloff"]
    assert len(k) == 2 and -0.4 < k[0] < -0.2  # numbers, not "auto": what the checkpoint and metrics keep
    again = train(dataset, tmp_path, TrainConfig(lens_falloff="auto", iterations=3, num_points=500), resume=True,
                  given={"lens_falloff": "--lens-falloff auto", "iterations": "--iterations 3"})
    assert again["settings"]["lens_falloff"] == k and again["iterations"] == 3
    assert "lens falloff measured" not in capsys.readouterr().err  # not measured again
