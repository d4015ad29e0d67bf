"""Initial points from structure-from-motion (stg_train.data.sfm): pycolmap SIFT + matching +
triangulation with the known poses on a textured synthetic scene; cache, frame selection, fallback."""
import numpy as np
import pytest

import stg_train  # noqa: F401  (sets the OpenMP policy before torch is imported)
from stg_train.data import DataError, Dataset, load_n3v
from stg_train.data import sfm
from stg_train.data.points import initial_points
from stg_train.data.volume import sample_view_volume
from stg_train.synthetic import SyntheticScene

FPS, FRAMES = 30.0, 2


@pytest.fixture(scope="module")
def scene_dir(synthetic_n3v):
    return synthetic_n3v("sfm_scene", num_cameras=8, num_frames=FRAMES, fps=FPS, width=160, height=120)


@pytest.fixture(scope="module")
def dataset(scene_dir):
    return load_n3v(scene_dir, prefer_png=True)


@pytest.fixture(scope="module")
def points(dataset):
    """sfm_points of every frame, cached in the dataset's own cache folder."""
    calls = []
    result = sfm.sfm_points(dataset, progress=lambda done, total: calls.append((done, total)))
    return result, calls


def surface_error(scene, dataset, xyz, seconds):
    """(N,) smallest relative depth error of each point over the training cameras: |z - true depth at
    the pixel it projects to| / true depth (inf where no camera sees it)."""
    best = np.full(len(xyz), np.inf)
    for ci in dataset.train_cameras:
        cam = dataset.cameras[ci]
        _, depth = scene.render(cam, seconds, return_depth=True)
        uv, z = cam.project(xyz)
        u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        rel = np.full(len(xyz), np.inf)
        rel[ok] = np.abs(z[ok] - depth[v[ok], u[ok]]) / depth[v[ok], u[ok]]
        best = np.minimum(best, rel)
    return best


def test_sfm_points_lie_on_the_true_surfaces(dataset, points):
    (xyz, rgb, t_center), calls = points
    assert calls == [(1, 2), (2, 2)]
    assert xyz.shape[1] == 3 and xyz.dtype == np.float32 and rgb.shape == xyz.shape
    assert 0 <= rgb.min() and rgb.max() <= 1
    # frame 0 keeps all its points (~370 measured), frame 1 a quarter of its own (~90)
    counts = {t: int(np.sum(t_center == t)) for t in np.unique(t_center)}
    assert sorted(counts) == [0.0, 0.5]
    assert counts[0.0] >= 200 and 0.15 * counts[0.0] <= counts[0.5] <= 0.4 * counts[0.0]
    scene = SyntheticScene(seed=0, duration=FRAMES / FPS)
    err = np.concatenate([surface_error(scene, dataset, xyz[t_center == t], t * FRAMES / FPS) for t in counts])
    # measured: median 0.85 %, 88 % within 5 %, 99.3 % within 25 % (1 px of disparity is ~10 % of the
    # depth at the far wall with this 160x120 rig)
    assert np.median(err) < 0.02
    assert np.mean(err < 0.05) > 0.8
    assert np.mean(err < 0.25) > 0.97


def test_second_call_reads_the_cache(dataset, points, monkeypatch):
    (xyz, rgb, t_center), _ = points
    assert list((dataset.path / ".stg_cache" / "sfm").glob("sfm_*.npz"))

    def no_pycolmap(*args, **kwargs):
        raise AssertionError("pycolmap ran although the result is cached")

    monkeypatch.setattr(sfm, "frame_points", no_pycolmap)
    again = sfm.sfm_points(dataset, progress=lambda done, total: pytest.fail("progress on a cached result"))
    for a, b in zip((xyz, rgb, t_center), again):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(AssertionError, match="pycolmap ran"):  # other settings: not this cache
        sfm.sfm_points(dataset, every=2)


def fake_dataset(num_frames=5, width=64, height=48, value=None, seed=0, bounds=(1.0, 8.0)):
    cams = SyntheticScene().cameras(6, width, height)
    rng = np.random.default_rng(seed)
    shape = (len(cams), num_frames, height, width, 3)
    frames = rng.integers(0, 256, shape, dtype=np.uint8) if value is None else np.full(shape, value, np.uint8)
    return Dataset(cams, frames, FPS, test_cameras=[0], bounds=None if bounds is None else np.tile(bounds, (6, 1)))


def test_every_selects_frames_and_sets_their_times(monkeypatch, tmp_path):
    ds = fake_dataset(num_frames=5)
    seen = []

    def stub(dataset, frame, work_dir, **kwargs):
        seen.append(frame)
        rng = np.random.default_rng(frame)
        return rng.normal(size=(40, 3)), np.full((40, 3), frame / 10, np.float32)

    monkeypatch.setattr(sfm, "frame_points", stub)
    xyz, rgb, t_center = sfm.sfm_points(ds, every=2, cache_dir=tmp_path)
    assert seen == [0, 2, 4]
    times, counts = np.unique(t_center, return_counts=True)
    np.testing.assert_allclose(times, [0, 0.4, 0.8])
    assert counts.tolist() == [40, 10, 10]  # the first frame keeps all, the others a quarter
    np.testing.assert_allclose(rgb[:, 0], t_center * 5 / 10, atol=1e-6)  # colours stay with their frame
    sfm.sfm_points(ds, frames=[1, 2, 3], every=2, cache_dir=tmp_path)
    assert seen[3:] == [1, 3]
    with pytest.raises(ValueError, match="out of range"):
        sfm.sfm_points(ds, frames=[7], cache_dir=tmp_path)


def test_farthest_point_sampling_keeps_the_outliers():
    rng = np.random.default_rng(1)
    cluster = rng.normal(scale=0.01, size=(100, 3))
    far = np.array([[5.0, 0, 0], [0, 5, 0], [0, 0, 5], [-5, 0, 0]])
    idx = sfm.farthest_point_indices(np.concatenate([cluster, far]), 5, rng)
    assert len(set(idx.tolist())) == 5 and {100, 101, 102, 103} <= set(idx.tolist())


def test_blank_scene_falls_back_to_the_view_volume():
    ds = fake_dataset(num_frames=2, value=128)  # untextured: no SIFT features, no points
    assert len(sfm.sfm_points(ds)[0]) == 0
    with pytest.warns(UserWarning, match="structure-from-motion found only 0 points"):
        init = initial_points(ds, "sfm", 60, np.random.default_rng(3))
    assert init.method == "volume" and init.volume_points == 60
    expected = sample_view_volume(ds, 60, np.random.default_rng(3))
    for a, b in zip((init.xyz, init.rgb, init.t_center), expected):
        np.testing.assert_array_equal(a, b)
    ds.bounds = None  # a layout without near/far bounds: no fallback, a clear error
    with pytest.raises(DataError, match="found only 0 points.*no near/far depth bounds"):
        initial_points(ds, "sfm", 60, np.random.default_rng(3))
    with pytest.raises(DataError, match="found only 0 points.*no near/far depth bounds"):
        initial_points(ds, "combined", 60, np.random.default_rng(3))
    with pytest.raises(DataError, match="needs near/far depth bounds"):
        initial_points(ds, "volume", 60, np.random.default_rng(3))


def test_trainer_starts_from_sfm_points(dataset, points):
    from stg_train.trainer import Trainer, TrainConfig

    (xyz, _, t_center), _ = points
    trainer = Trainer(dataset, TrainConfig(init="sfm", num_points=100000, iterations=1, model="lite"))
    np.testing.assert_allclose(trainer.params["xyz"].detach().numpy(), xyz, atol=1e-6)
    np.testing.assert_allclose(trainer.params["t_center"].detach().numpy()[:, 0], t_center)
    capped = Trainer(dataset, TrainConfig(init="sfm", num_points=150, iterations=1, model="lite"))
    kept = capped.params["xyz"].detach().numpy()
    assert kept.shape == (150, 3)
    assert np.all(np.min(np.linalg.norm(kept[:, None] - xyz[None], axis=-1), axis=1) < 1e-6)  # a subset
    with pytest.raises(ValueError, match="init must be"):
        Trainer(dataset, TrainConfig(init="colmap", iterations=1))


def test_cli_init_options(dataset):
    from stg_train.cli.train import build_parser as build_train_parser
    from stg_train.data.points import default_method as default_init

    args = build_train_parser().parse_args(["data", "--out", "o"])
    assert (args.init, args.init_every) == ("auto", 1)
    assert default_init(dataset) == "volume"  # N3V has near/far bounds
    assert default_init(fake_dataset(num_frames=1, bounds=None)) == "volume"  # bounds from the SfM points
    args = build_train_parser().parse_args(["data", "--init", "volume", "--init-every", "5"])
    assert (args.init, args.init_every) == ("volume", 5)
    with pytest.raises(SystemExit):
        build_train_parser().parse_args(["data", "--init-every", "0"])
