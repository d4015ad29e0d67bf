"""stg_runtime.render_load against a brute-force count with the spec's float64 rules."""
from __future__ import annotations

import numpy as np
import pytest

from stg_runtime.demo import TRAINED_LAYERS, like_trained_model, random_model
from stg_runtime.render_load import render_load, scene_load
from stg_runtime.spec import MAX_ALPHA, MIN_ALPHA, T_STOP, project_oracle
from stg_runtime.timeeval import evaluate

from tests.scenes import clean_scenes


def brute_force_load(means, quats, scales, opacities, camera):
    """Per pixel, the Gaussians composited before the pixel stops; per Gaussian in view, the pixels of
    its footprint with alpha >= 1/255 (sorted); per pixel, whether it stopped: every Gaussian against
    every pixel, in float64, in depth order."""
    proj = project_oracle(means, quats, scales, camera)
    opacities = np.asarray(opacities, np.float64)
    px = (np.arange(camera.width) + 0.5)[None, :]
    py = (np.arange(camera.height) + 0.5)[:, None]
    T = np.ones((camera.height, camera.width))
    stopped = np.zeros_like(T, dtype=bool)
    layers = np.zeros_like(T, dtype=np.int64)
    footprints = []
    for i in np.argsort(proj.depth, kind="stable"):
        if not proj.visible[i] or opacities[i] < MIN_ALPHA:
            continue
        dx, dy = px - proj.mean2d[i, 0], py - proj.mean2d[i, 1]
        A, B, C = proj.conic[i]
        power = 0.5 * (A * dx * dx + C * dy * dy) + B * dx * dy
        alpha = np.minimum(MAX_ALPHA, opacities[i] * np.exp(-power))
        reach = (np.abs(dx) <= proj.radius[i]) & (np.abs(dy) <= proj.radius[i]) & (power >= 0) & (alpha >= MIN_ALPHA)
        if reach.any():
            footprints.append(int(reach.sum()))
        take = reach & ~stopped
        t_next = T * (1 - alpha)
        add = take & (t_next >= T_STOP)
        stopped |= take & (t_next < T_STOP)
        layers += add
        T = np.where(add, t_next, T)
    return layers, sorted(footprints), stopped


@pytest.mark.parametrize("size, m, seed", [((48, 32), 300, 0), ((37, 29), 200, 1)])
def test_matches_brute_force(size, m, seed):
    for arrays, camera, _ in clean_scenes(seed, 2, m, *size, 1, opacity=(0.6, 1.0), size=(1.0, 10.0)):
        load = render_load(*arrays[:4], camera)
        layers, footprints, stopped = brute_force_load(*arrays[:4], camera)
        assert layers.max() >= 5 and stopped.any() and not stopped.all()
        np.testing.assert_array_equal(load.layers, layers)
        assert load.in_view == len(footprints)
        assert sorted(load.footprints.tolist()) == footprints
        assert load.total == m
        assert load.mean_layers == pytest.approx(layers.mean())
        assert load.p99_layers == pytest.approx(np.percentile(layers, 99))
        assert load.mean_footprint == pytest.approx(np.mean(footprints))


def test_opaque_stack_stops():
    """Opaque Gaussians stacked in front of the camera: every pixel they cover stops after the number of
    layers that brings T below 1e-4: at alpha 0.93 to 0.95 three are composited (T 1.25e-4 to 3.3e-4
    after them), the fourth stops the pixel."""
    model = random_model(1, "lite", width=32, height=32)
    cam = model.cameras[0]
    n = 10
    means = np.tile([0.0, 0.0, 5.0], (n, 1)) + np.arange(n)[:, None] * [0, 0, 0.1]
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    scales = np.full((n, 3), 20.0)  # far wider than the view: alpha 0.93 to 0.95 on every pixel
    load = render_load(means, quats, scales, np.full(n, 0.95), cam)
    assert np.all(load.layers == 3)
    assert load.in_view == n and np.all(load.footprints == 32 * 32)
    assert load.tile_entries == n * 4


def test_scene_load_evaluates_time():
    model = random_model(400, "full", width=64, height=40, seed=3)
    cam = model.cameras[0]
    t = 0.4 * model.duration
    segment, tau = model.segment_at(t)
    g = evaluate(segment, tau)
    expected = render_load(g.means, g.quats, g.scales, g.opacities, cam)
    got = scene_load(model, cam, t)
    np.testing.assert_array_equal(got.layers, expected.layers)
    assert got.as_dict() == expected.as_dict() and "layers/pixel" in got.summary()


def test_like_trained_scene_scales_with_resolution():
    """like_trained_model: the layers per pixel stay near TRAINED_LAYERS at any resolution and count,
    and the footprints grow with the image (4x the pixels, about 4x the area), unlike random_model's."""
    loads = {}
    for n, (w, h) in [(20000, (320, 180)), (20000, (640, 360)), (60000, (640, 360))]:
        model = like_trained_model(n, w, h, seed=2)
        loads[n, w] = scene_load(model, model.cameras[0], 0.5 * model.duration)
    for load in loads.values():
        assert 0.8 * TRAINED_LAYERS < load.mean_layers < 1.25 * TRAINED_LAYERS
        assert 1.3 < load.p99_layers / load.mean_layers < 2.2
        assert load.in_view > 0.8 * load.total
    assert 3.3 < loads[20000, 640].mean_footprint / loads[20000, 320].mean_footprint < 4.7
    assert 2.5 < loads[20000, 640].mean_footprint / loads[60000, 640].mean_footprint < 3.5
    small, large = (random_model(20000, width=w, height=h) for w, h in [(320, 180), (640, 360)])
    ratio = (scene_load(large, large.cameras[0], 0.5).mean_footprint
             / scene_load(small, small.cameras[0], 0.5).mean_footprint)
    assert ratio < 1.5
