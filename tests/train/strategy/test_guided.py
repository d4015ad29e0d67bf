"""Guided sampling (stg_train.strategy.guided) and the ablation switches (TrainConfig.frozen) on a tiny scene."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_train.data import load_n3v  # noqa: E402
from stg_train.strategy.guided import GuidedSampling, GuidedSettings, coarse_depth, error_pixels  # noqa: E402
from stg_train.params import COMPONENTS, STATIC_T_SCALE, STGParams  # noqa: E402
from stg_train.strategy import Schedule, StepContext  # noqa: E402
from stg_train.strategy.ops import keep_gaussians  # noqa: E402
from stg_train.synthetic import SyntheticScene, write_n3v  # noqa: E402
from stg_train.trainer import Trainer, TrainConfig  # noqa: E402

SCENE = dict(num_cameras=4, num_frames=2, fps=2.0, width=96, height=72)
#: No density control, no opacity reset: only guided sampling changes the number of Gaussians.
QUIET = {"refine_start": 10 ** 6, "reset_every": 0, "outside_at": 0}


pytestmark = pytest.mark.usefixtures("two_torch_threads")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("guided_scene")
    write_n3v(path, SyntheticScene(seed=0, duration=1.0), **SCENE)
    return load_n3v(path, prefer_png=True)


def _context(trainer, gt_of):
    ds = trainer.dataset
    return StepContext(ds, 0, 0.0, [], lambda ci, t: trainer.render(ds.cameras[ci], t), gt_of)


@pytest.fixture(scope="module")
def half_scene(dataset):
    """A trainer whose Gaussians right of 40% of the first training camera's image were removed, the 'ground
    truth' being the render before the removal: only that region is wrong. The Gaussians start at rest, so
    that each is drawn where its xyz projects."""
    trainer = Trainer(dataset, TrainConfig(iterations=1, num_points=1500, guided=False, motion_init="zero"))
    ci = dataset.train_cameras[0]
    cam = dataset.cameras[ci]
    with torch.no_grad():
        gt = trainer.render(cam, 0.0)[0].clamp(0, 1)
    uv, _ = cam.project(trainer.params["xyz"].detach().numpy())
    keep_gaussians(trainer.params, trainer.optimizer, torch.as_tensor(uv[:, 0] < 0.4 * cam.width))
    return trainer, ci, gt


def test_adds_gaussians_in_high_error_patches(half_scene):
    trainer, ci, gt = half_scene
    cam, ds = trainer.dataset.cameras[ci], trainer.dataset
    far = float(ds.bounds[ci][1])
    params = trainer.params
    before = params.count
    with torch.no_grad():
        image, out = trainer.render(cam, 0.0)
    image = image.clamp(0, 1)
    mask = error_pixels(image, gt)
    assert mask.sum() > 200
    cols = torch.nonzero(mask)[:, 1]
    assert cols.min() >= 0.4 * cam.width - 4  # the error patches lie in the emptied region only
    depth = coarse_depth(out.depth, out.alpha, far)

    torch.manual_seed(1)
    context = _context(trainer, lambda c, j: gt)
    added, score = GuidedSampling(Schedule()).sample_view(params, trainer.optimizer, context, ci)
    assert score < 0.88 and added == 2 * int(mask.sum()) and params.count == before + added
    new = {k: v[before:].detach() for k, v in params.raw.items()}
    # every new Gaussian lies on the ray of an error pixel of a selected patch
    uv, z = cam.project(new["xyz"].numpy().astype(np.float64))
    u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    assert mask.numpy()[v, u].all()
    np.testing.assert_allclose(uv, np.floor(uv) + 0.5, atol=1e-3)
    # ground-truth colour (the full model stores its logit), opacity 0.1, random temporal centre, at rest
    np.testing.assert_allclose(torch.sigmoid(new["features"][:, :3]).numpy(), gt.numpy()[v, u].clip(0.02, 0.98),
                               atol=1e-5)
    np.testing.assert_allclose(torch.sigmoid(new["opacity_logit"]).numpy(), 0.1, atol=1e-6)
    t = new["t_center"].numpy()
    assert t.min() >= 0 and t.max() < 1 and t.std() > 0.1
    assert (new["motion"] == 0).all() and (new["omega"] == 0).all() and (new["features"][:, 3:] == 0).all()
    # depths: 0.7 d and min(7.5 d, far) (+-5%), d the patch's coarse depth (the far bound where empty)
    d = depth.numpy()[v, u]
    k = len(z) // 2
    assert np.all(np.abs(z[:k] / (0.7 * d[:k]) - 1) <= 0.05 + 1e-6)
    assert np.all(np.abs(z[k:] / np.minimum(7.5 * d[k:], far) - 1) <= 0.05 + 1e-6)
    assert z.max() <= 1.05 * far + 1e-6


def test_reference_depth_is_the_views_largest_rendered_depth(half_scene):
    trainer, ci, gt = half_scene
    cam, ds = trainer.dataset.cameras[ci], trainer.dataset
    far = float(ds.bounds[ci][1])
    with torch.no_grad():
        image, out = trainer.render(cam, 0.0)
    settings = GuidedSettings(depth="max")
    torch.manual_seed(1)
    new = GuidedSampling(Schedule(), settings).new_gaussians(trainer.params, cam, image.clamp(0, 1), gt, out.depth,
                                                             out.alpha, far)
    _, z = cam.project(new["xyz"].numpy().astype(np.float64))
    d = float(out.depth[out.alpha >= settings.min_alpha].max())  # one depth for the whole view
    k = len(z) // 2
    np.testing.assert_allclose(z[:k] / (0.7 * d), 1, atol=0.05 + 1e-6)
    np.testing.assert_allclose(z[k:] / min(7.5 * d, far), 1, atol=0.05 + 1e-6)


def _trainer_and_renders(dataset):
    """A fresh trainer and its renders of every training view at time 0 (clamped to [0, 1])."""
    trainer = Trainer(dataset, TrainConfig(iterations=1, num_points=500, guided=False, depth_candidates=0))
    with torch.no_grad():
        renders = {ci: trainer.render(dataset.cameras[ci], 0.0)[0].clamp(0, 1) for ci in dataset.train_cameras}
    return trainer, renders


def test_reference_needs_two_views_below_the_threshold(dataset):
    trainer, renders = _trainer_and_renders(dataset)
    bad = dataset.train_cameras[0]
    gt = {ci: (1 - r if ci == bad else r) for ci, r in renders.items()}  # one view far off, the others perfect
    context = _context(trainer, lambda ci, j: gt[ci])
    assert GuidedSampling(Schedule()).choose_views(context) == [bad]
    assert GuidedSampling(Schedule(), GuidedSettings(min_views=2)).choose_views(context) == []


def test_nothing_added_when_ssim_is_high(dataset):
    trainer, renders = _trainer_and_renders(dataset)
    context = _context(trainer, lambda ci, j: renders[ci])  # the model is perfect: SSIM 1
    guided = GuidedSampling(Schedule())
    assert guided.choose_views(context) == []
    before = trainer.params.count
    added, score = guided.sample_view(trainer.params, trainer.optimizer, context, dataset.train_cameras[0])
    assert added == 0 and score > 0.99 and trainer.params.count == before


def _run(dataset, tmp_path, guided=True, kill_at=None, out="run"):
    """7 steps from 100 initial points (sparse: large empty patches), guided sampling at steps 3 and 5."""
    cfg = TrainConfig(iterations=7, num_points=100, depth_candidates=0, guided=guided, checkpoint_every=4,
                      schedule={**QUIET, "guided_start": 3, "guided_every": 2})
    trainer = Trainer(dataset, cfg, out_dir=tmp_path / out)

    def kill(t):
        if t.step == kill_at:
            raise KeyboardInterrupt

    try:
        trainer.train(progress=False, callback=kill)
    except KeyboardInterrupt:
        trainer = Trainer.resume(dataset, tmp_path / out / "checkpoint.pt")
        assert trainer.step == 4
        trainer.train(progress=False)
    return trainer


@pytest.fixture
def one_thread():
    """Bit-exact comparisons: with 2 threads the splatter's feature gradients are not bit-reproducible at
    this image size (the backward of a gather accumulates in a thread-dependent order)."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def test_trainer_runs_guided_sampling_and_resumes_to_the_same_state(dataset, tmp_path, one_thread):
    off = _run(dataset, tmp_path, guided=False, out="off")
    assert off.params.count == 100 and len(off.strategies) == 1
    on = _run(dataset, tmp_path, out="on")
    log = on.strategies[1].log
    assert [e["step"] for e in log] == [3, 5] and all(e["added"] > 0 for e in log)
    assert on.params.count == 100 + sum(e["added"] for e in log)
    assert len(on.strategies[0].grad_sum) == on.params.count  # DensityControl's statistics follow
    assert on.optimizer.state[on.params.raw["xyz"]]["exp_avg"].shape[0] == on.params.count  # and Adam's
    resumed = _run(dataset, tmp_path, kill_at=6, out="resumed")  # checkpoint at 4, between the samplings
    assert resumed.strategies[1].log == log
    for name in on.params.raw:
        assert torch.equal(on.params.raw[name], resumed.params.raw[name]), name
    sa, sb = on.optimizer.state_dict()["state"], resumed.optimizer.state_dict()["state"]
    for k in sa:
        assert torch.equal(sa[k]["exp_avg"], sb[k]["exp_avg"]) and torch.equal(sa[k]["exp_avg_sq"], sb[k]["exp_avg_sq"])


def test_ablation_switches_freeze_their_parameters(dataset):
    cfg = dict(iterations=4, num_points=300, depth_candidates=0, guided=False, schedule=QUIET)
    frozen = Trainer(dataset, TrainConfig(**cfg, frozen=("temporal_opacity", "motion", "rotation")))
    start = {k: v.detach().clone() for k, v in frozen.params.raw.items()}
    frozen.train(progress=False)
    raw = frozen.params.raw
    assert (raw["motion"] == 0).all() and (raw["omega"] == 0).all()
    assert (raw["t_scale_raw"] == STATIC_T_SCALE).all() and torch.equal(raw["t_center"], start["t_center"])
    for name in ("time_features", "features", "xyz"):  # what is not frozen trains
        assert not torch.equal(raw[name], start[name]), name
    groups = {g["name"] for g in frozen.optimizer.param_groups}
    assert not groups & {"motion", "omega", "t_center", "t_scale_raw"} and "time_features" in groups

    full = Trainer(dataset, TrainConfig(**cfg))
    full.train(progress=False)
    assert (full.params["motion"] != 0).any() and (full.params["omega"] != 0).any()
    assert (full.params["t_scale_raw"] != 0).any()

    static = STGParams.from_points(np.zeros((4, 3)) + np.arange(4)[:, None], np.full((4, 3), 0.5), np.zeros(4),
                                   static=True)
    assert static.static and static.frozen == tuple(sorted(COMPONENTS))
    assert not any(static.trainable(n) for n in ("motion", "omega", "time_features", "t_center", "t_scale_raw"))
    with pytest.raises(ValueError, match="wobble"):
        Trainer(dataset, TrainConfig(**cfg, frozen=("wobble",)))
