"""stg_train.convert.finetune: the raw round trip, fine-tuning raises PSNR, pruning by contribution, files
read back, clear errors."""
from types import SimpleNamespace

import numpy as np
import pytest

from stg_runtime import Camera, Model, Player, Segment
from stg_runtime import format as stg_format
from stg_train.cli.convert import main
from stg_train.convert.compress import (SAFETY, Views, budget_mse, compress, dataset_views, importance, mse,
                                        prune_least_important, render_views)
from stg_train.convert.finetune import (_segment_of, compress_finetuned, contribution, finetune, finetune_file,
                                        params_of, prune_schedule)
from stg_train.data import load_dataset
from stg_train.metrics import psnr_of_mse


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """(dataset folder, dataset, trained .stg path): 4 cameras x 3 frames, 40x30, 40 training steps."""
    import torch

    from stg_train.export import export_trainer
    from stg_train.synthetic import SyntheticScene, write_n3v
    from stg_train.trainer import TrainConfig, Trainer

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("ft")
    write_n3v(root / "data", SyntheticScene(seed=0, duration=0.1), num_cameras=4, num_frames=3, fps=30,
              width=40, height=30)
    ds = load_dataset(root / "data")
    trainer = Trainer(ds, TrainConfig(iterations=40, num_points=400, splatter="torch"))
    trainer.train(progress=False)
    return root / "data", ds, export_trainer(trainer, root / "model.stg", check=False).path


def train_psnr(model: Model, ds) -> float:
    pairs = [(ds.cameras[c], j / ds.fps) for c in ds.train_cameras for j in range(ds.num_frames)]
    refs = [ds.image(c, j) for c in ds.train_cameras for j in range(ds.num_frames)]
    return psnr_of_mse(mse(render_views(model, Views(pairs, refs)), refs))


def test_raw_round_trip_is_exact_to_float32(scene):
    model = stg_format.load(scene[2])
    seg = model.segments[0]
    back = _segment_of(params_of(seg, model.kind), seg)
    for name in ("opacity", "t_center", "t_scale", "position", "rotation", "scale", "features"):
        np.testing.assert_allclose(getattr(back, name), getattr(seg, name), rtol=1e-5, atol=1e-6)
    assert back.decoder == seg.decoder


def test_finetuning_recovers_what_pruning_lost(scene):
    _, ds, path = scene
    model = stg_format.load(path)
    pruned = Model(model.kind, model.fps, [prune_least_important(model.segments[0], 0.5)], model.cameras,
                   model.bounds)
    tuned = finetune(pruned, ds, 30)
    assert tuned.segments[0].count == pruned.segments[0].count
    assert train_psnr(tuned, ds) > train_psnr(pruned, ds) + 0.1


def test_the_command_line_names_the_libraries_defaults():
    from stg_train.cli import convert as cli
    from stg_train.convert import finetune as library
    from stg_train.convert.compress import PRESETS

    assert cli.PRESET_NAMES == tuple(PRESETS) and cli.PRUNE_STAGES == library.PRUNE_STAGES


def test_prune_schedule_spreads_equal_shares_over_the_first_half():
    assert prune_schedule(1000, 100, 0.0, 5) == {}
    assert prune_schedule(1000, 100, 0.6, 1) == {0: 400}
    schedule = prune_schedule(1000, 100, 0.6, 4)
    assert list(schedule) == [0, 12, 25, 37] and schedule[37] == 400
    kept = [1000] + list(schedule.values())
    shares = [b / a for a, b in zip(kept, kept[1:])]
    assert max(shares) - min(shares) < 0.01 and all(a > b for a, b in zip(kept, kept[1:]))
    assert prune_schedule(1000, 4, 0.6, 5) == {0: 632, 1: 400}  # no more stages than steps in the span
    assert prune_schedule(1000, 0, 0.5, 3) == {0: 500}


def test_gradual_pruning_keeps_those_that_contribute_most(scene):
    """Pruned in stages while fine-tuning: the count the schedule says and what is left renders; at no
    steps and one stage, exactly the Gaussians of highest contribution are kept."""
    _, ds, path = scene
    model = stg_format.load(path)
    seg = model.segments[0]
    tuned = finetune(model, ds, 20, prune=0.5, stages=3)
    assert tuned.segments[0].count == seg.count - int(0.5 * seg.count)
    assert np.isfinite(train_psnr(tuned, ds))
    at_once = finetune(model, ds, 0, prune=0.5)
    keep = np.zeros(seg.count, bool)
    keep[np.argsort(contribution(params_of(seg, model.kind), ds, seed=0), kind="stable")[seg.count // 2:]] = True
    np.testing.assert_allclose(at_once.segments[0].position, seg.subset(keep).position, rtol=1e-5, atol=1e-6)


def one_view(camera) -> SimpleNamespace:
    """A stand-in dataset of one training camera at one frame (tau 0): contribution's views are all it."""
    return SimpleNamespace(train_cameras=[0], cameras=[camera], num_frames=1)


def test_contribution_is_the_blending_weight_the_views_show(scene):
    """Summed over the Gaussians, the contribution of 3 views of one image is 3 times that image's
    alpha, as the torch splatter (the twin of the numba one contribution uses) renders it."""
    import torch

    from stg_train.render import rasterize

    _, ds, path = scene
    model = stg_format.load(path)
    params = params_of(model.segments[0], model.kind)
    camera = ds.cameras[ds.train_cameras[0]]
    score = contribution(params, one_view(camera), views=3)
    with torch.no_grad():
        g = params.at(0.0)
        alpha = rasterize(g.means, g.quats, g.scales, g.opacities, g.features, camera, backend="torch").alpha
    assert score.shape == (params.count,) and (score >= 0).all()
    np.testing.assert_allclose(score.sum(), 3 * float(alpha.sum()), rtol=1e-4)


def test_contribution_sees_occlusion():
    """Two equal Gaussians on the camera's axis, 1 and 3 units away: importance ranks them alike;
    contribution gives the one behind less than a fifth of what it has alone."""
    cam = Camera.look_at((0, 0, 0), (0, 0, 1), (0, -1, 0), 60, 32, 32)

    def gaussians(depths):
        n = len(depths)
        position = np.zeros((n, 4, 3), np.float32)
        position[:, 0, 2] = depths
        rotation = np.zeros((n, 2, 4), np.float32)
        rotation[:, 0, 0] = 1.0
        return Segment(0, 1, opacity=np.full(n, 0.99, np.float32), t_center=np.zeros(n, np.float32),
                       t_scale=np.zeros(n, np.float32), position=position, rotation=rotation,
                       scale=np.full((n, 3), 0.5, np.float32), features=np.full((n, 3), 0.5, np.float32))

    both = gaussians([1.0, 3.0])
    assert importance(both)[0] == importance(both)[1]
    front, back = contribution(params_of(both, "lite"), one_view(cam), views=1)
    (alone,) = contribution(params_of(gaussians([3.0]), "lite"), one_view(cam), views=1)
    assert back < 0.2 * alone and back < 0.2 * front


def test_the_search_keeps_a_margin_unless_it_sees_every_held_out_frame(scene):
    _, ds, path = scene
    model = stg_format.load(path)
    some, every = dataset_views(ds, model, 2), dataset_views(ds, model, ds.num_frames)
    assert len(some.pairs) == 2 and not some.complete and every.complete
    for views, share in ((some, SAFETY), (every, 1.0)):
        _, settings = compress(model, "web", views=views)
        model_mse = mse(render_views(model, views), views.references)
        assert settings.budget_mse == pytest.approx(budget_mse(share * 0.3, model_mse), rel=1e-9)


def test_what_fine_tuning_gains_the_search_may_spend(scene):
    _, ds, path = scene
    _, settings, info = compress_finetuned(stg_format.load(path), ds, 20, "web", 0.2)
    gain = info.psnr_finetuned - info.psnr_original
    assert gain > 0.5  # the 40-step model is far from converged
    tuned_mse = 10.0 ** (-info.psnr_finetuned / 10.0)
    assert settings.budget_mse == pytest.approx(budget_mse(0.3 + gain, tuned_mse), rel=1e-6)


def test_finetuned_web_file_reads_back_in_the_runtime(scene, tmp_path):
    _, ds, path = scene
    rep, info = finetune_file(path, tmp_path / "out.stg", ds, 10, "web", 0.3)
    player = Player(tmp_path / "out.stg", device="cpu")
    assert np.isfinite(player.render(ds.cameras[0], 0.0)).all()
    assert info.kept == stg_format.load(path).segments[0].count - int(0.3 * info.gaussians)
    assert rep.file_after < rep.file_before and stg_format.load(tmp_path / "out.stg").provenance["compress"]["finetune"]


def test_cli_finetune_and_bad_input(scene, tmp_path, capsys):
    data, ds, path = scene
    rc = main(["compress", str(path), str(tmp_path / "o.stg"), "--preset", "web", "--data", str(data),
               "--finetune", "5", "--prune-fraction", "0.2"])
    out = capsys.readouterr().out
    assert rc == 0 and "fine-tune" in out and (tmp_path / "o.stg").exists()
    assert main(["compress", str(path), str(tmp_path / "x.stg"), "--finetune", "5"]) == 2
    assert "--data" in capsys.readouterr().err
    assert main(["compress", str(path), str(tmp_path / "x.stg"), "--data", str(data), "--finetune", "5",
                 "--level", "6"]) == 2
    assert "--level" in capsys.readouterr().err and not (tmp_path / "x.stg").exists()
    model = stg_format.load(path)
    seg = model.segments[0]
    later = Segment(seg.num_frames, seg.num_frames, decoder=seg.decoder, activation=seg.activation, **seg.arrays())
    two = Model(model.kind, model.fps, [seg, later], model.cameras, model.bounds)
    stg_format.save(two, tmp_path / "two.stg")
    assert main(["compress", str(tmp_path / "two.stg"), str(tmp_path / "y.stg"), "--data", str(data),
                 "--finetune", "5"]) == 2
    err = capsys.readouterr().err
    assert "two.stg" in err and "one-segment" in err and not (tmp_path / "y.stg").exists()
