"""stg_train.convert.still and fine-tuning's still Gaussians: travel is the distance motion adds while
drawn, the still ones end with no motion and no rotation velocity, the others keep theirs."""
import numpy as np

from stg_runtime import Segment
from stg_runtime import format as stg_format
from stg_train.convert.finetune import _still_count, finetune
from stg_train.convert.still import still_mask, travel
from stg_train.params import extent_of

from .test_finetune import scene  # noqa: F401  (the module's fixture)


def segment(velocity, t_center, t_scale, opacity, frames=10) -> Segment:
    n = len(velocity)
    position = np.zeros((n, 4, 3), np.float32)
    position[:, 0] = [1.0, 2.0, 3.0]
    position[:, 1, 0] = velocity
    rotation = np.zeros((n, 2, 4), np.float32)
    rotation[:, 0, 0] = 1.0
    return Segment(0, frames, np.asarray(opacity, np.float32), np.asarray(t_center, np.float32),
                   np.asarray(t_scale, np.float32), position, rotation, np.full((n, 3), 0.1, np.float32),
                   np.zeros((n, 3), np.float32))


def test_travel_is_the_farthest_offset_motion_adds_while_drawn():
    # drawn at every frame j / 10, temporal centre 0.5: the farthest frame is 0 (d = -0.5)
    # narrow window (t_scale 1e4 around 0.5): drawn only where opacity exp(-1e4 d^2) >= 1/255, d = 0
    # never drawn (opacity 0); centre 2 beyond the segment, drawn: d reaches 2 at frame 0
    seg = segment([2.0, 2.0, 2.0, 0.5], [0.5, 0.5, 0.5, 2.0], [0.0, 1e4, 0.0, 0.0], [0.9, 0.9, 0.0, 0.9])
    np.testing.assert_allclose(travel(seg), [1.0, 0.0, 0.0, 1.0], atol=1e-6)
    assert still_mask(seg, 0.5).tolist() == [False, True, True, False]


def test_travel_follows_the_cubic_motion():
    seg = segment([0.0], [0.0], [0.0], [0.9])
    seg.position[0, 3] = [0.0, 0.0, 8.0]  # 8 d^3 along z; d = 0.9 at the last frame
    np.testing.assert_allclose(travel(seg), [8 * 0.9 ** 3], rtol=1e-6)


def test_finetuning_holds_the_still_gaussians_at_zero_velocity(scene):
    _, ds, path = scene
    model = stg_format.load(path)
    seg = model.segments[0]
    extent = extent_of([ds.cameras[i] for i in ds.train_cameras])
    distance = float(np.median(travel(seg)))
    still = still_mask(seg, distance)
    assert 0 < still.sum() < seg.count
    tuned = finetune(model, ds, 10, still=distance / extent).segments[0]
    velocity = np.abs(tuned.position[:, 1:]).sum(axis=(1, 2)) + np.abs(tuned.rotation[:, 1:]).sum(axis=(1, 2))
    assert np.all(velocity[still] == 0) and np.all(velocity[~still] > 0)
    assert _still_count(tuned) == still.sum()
    untouched = finetune(model, ds, 10).segments[0]
    assert _still_count(untouched) == 0

