"""Warm-started segments (stg_train.warm): the time axis re-based exactly, past Gaussians found."""
from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from stg_train.params import gaussians_at  # noqa: E402
from stg_train.segments import Span  # noqa: E402
from stg_train.warm import axis_map, extend_at_seam, past_gaussians, rebase_time  # noqa: E402


def _raw(n=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)  # noqa: E731
    return {"xyz": r(n, 3), "motion": r(n, 9), "features": r(n, 6), "time_features": r(n, 3),
            "log_scale": r(n, 3), "rotation": r(n, 4), "omega": r(n, 4), "opacity_logit": r(n, 1),
            "t_center": torch.rand(n, 1, generator=g, dtype=torch.float64), "t_scale_raw": r(n, 1) * 0.5}


def test_rebased_gaussians_are_the_same_at_every_video_frame():
    prev, span = Span(0, 0, 50), Span(1, 50, 40)
    a, b = axis_map(prev, span)
    raw = _raw()
    new = rebase_time(raw, a, b)
    for frame in (46, 50, 53, 60):
        old_g = gaussians_at(raw, (frame - prev.start) / prev.count)
        new_g = gaussians_at(new, (frame - span.start) / span.count)
        for x, y in zip(old_g, new_g):
            torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-12)


def test_past_gaussians():
    raw = _raw(3)
    raw["t_center"] = torch.tensor([[-3.0], [0.5], [1.2]], dtype=torch.float64)
    raw["t_scale_raw"] = torch.zeros(3, 1, dtype=torch.float64)
    raw["opacity_logit"] = torch.full((3, 1), 2.0, dtype=torch.float64)
    assert past_gaussians(raw, 0.0, 1.0).tolist() == [True, False, False]


def test_extended_gaussians_keep_the_first_frame_and_last_longer():
    """extend_at_seam: at tau = 0 the same Gaussians (float64); the widened ones move on a line and are
    more opaque later in the segment than the exact re-based ones; the others are untouched."""
    raw = _raw(200, seed=1)
    raw["t_center"] = raw["t_center"] * 0.6 - 0.5  # centres in [-0.5, 0.1]: some drawn at the seam
    raw["t_scale_raw"] = raw["t_scale_raw"] - 1.5
    new = extend_at_seam(raw, 1.0)
    for x, y in zip(gaussians_at(raw, 0.0), gaussians_at(new, 0.0)):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-12)
    alive = gaussians_at(raw, 0.0).opacities >= 0.005
    widened = alive & (torch.exp(raw["t_scale_raw"].reshape(-1)) < 1.0)
    assert 20 < int(widened.sum()) < int(alive.sum()) + 1 and int((~alive).sum()) > 20
    assert torch.all(gaussians_at(new, 0.5).opacities[widened] > gaussians_at(raw, 0.5).opacities[widened])
    assert torch.all(new["motion"][widened][:, 3:] == 0)
    for name in raw:
        torch.testing.assert_close(new[name][~widened], raw[name][~widened], rtol=0, atol=0)
    assert extend_at_seam(raw, 0.0)["t_scale_raw"].equal(raw["t_scale_raw"])


def test_a_warm_segment_starts_where_its_predecessor_ends(synthetic_n3v, tmp_path):
    """A warm chain of two segments trains; before any step, segment 1's Gaussians render its first
    frame as segment 0's do at that video frame (a context frame of segment 0)."""
    from stg_train.cli.train import main as train_main
    from stg_train.data import load_n3v
    from stg_train.export import GoldenDiff, trainer_render
    from stg_train.segments import plan_segments
    from stg_train.params import STGParams
    from stg_train.warm import warm_start

    scene = synthetic_n3v("warm_scene", num_cameras=4, num_frames=8, fps=4.0, width=64, height=48)
    out = tmp_path / "run"
    assert train_main([str(scene), "--out", str(out), "--segment-frames", "4", "--iterations", "8", "--points",
                       "200", "--init", "volume", "--segment-context", "1", "--segment-schedule", "warm",
                       "--quiet"]) == 0
    metrics = __import__("json").loads((out / "metrics.json").read_text())
    assert [s["warm"] for s in metrics["segments"]] == [False, True]
    plan = plan_segments(8, 4)
    start = warm_start(out / "segments" / "00" / "checkpoint.pt", plan[0], plan[1], (1, 0), "cpu", 1.0)
    state = torch.load(out / "segments" / "00" / "checkpoint.pt", map_location="cpu", weights_only=True)
    before = STGParams.from_state_dict(state["params"], "cpu")
    ds = load_n3v(scene, prefer_png=True)
    cam = ds.cameras[ds.test_cameras[0]]
    assert GoldenDiff.of(trainer_render(start.params, cam, 0.0), trainer_render(before, cam, 1.0)).ok
    # warm_points: the carried Gaussians first, then the segment's own initial points (over its time)
    from stg_train.segments import segment_view
    from stg_train.trainer import Trainer, TrainConfig
    view = segment_view(ds, plan[1], 1)
    config = TrainConfig(iterations=8, num_points=200, init="volume", warm_points=True)
    trainer = Trainer(view, config, tmp_path / "probe", warm=start)
    n = start.params.count
    assert trainer.params.count == n + len(trainer.initial.xyz) and len(trainer.initial.xyz) > 50
    torch.testing.assert_close(trainer.params["xyz"][:n].cpu(), start.params["xyz"].cpu(), rtol=0, atol=0)
    t = trainer.params["t_center"][n:].detach().reshape(-1)
    assert float(t.min()) >= 0.0 and float(t.max()) > 0.5


class _Killed(Exception):
    pass


def test_a_killed_warm_chain_resumes_where_it_stopped(synthetic_n3v, tmp_path, monkeypatch):
    """Killed inside the warm segment 1, --resume keeps segment 0, continues segment 1 from its checkpoint
    (still warm, its shorter schedule) and ends with the uninterrupted run's file."""
    import numpy as np

    from stg_runtime import format as stg_format
    from stg_train.cli.train import main as train_main
    from stg_train.trainer import Trainer

    scene = synthetic_n3v("warm_scene", num_cameras=4, num_frames=8, fps=4.0, width=64, height=48)
    args = ["--segment-frames", "4", "--iterations", "12", "--points", "200", "--init", "volume",
            "--segment-context", "0", "--segment-schedule", "warm", "--checkpoint-every", "1", "--quiet"]
    assert train_main([str(scene), "--out", str(tmp_path / "whole")] + args) == 0
    step = Trainer.train_step

    def killed(trainer):
        if trainer.warm and trainer.step == 2:
            raise _Killed
        return step(trainer)

    monkeypatch.setattr(Trainer, "train_step", killed)
    with pytest.raises(_Killed):
        train_main([str(scene), "--out", str(tmp_path / "killed")] + args)
    monkeypatch.undo()
    assert train_main([str(scene), "--out", str(tmp_path / "killed"), "--resume"] + args) == 0
    a, b = (stg_format.load(tmp_path / n / "model.stg") for n in ("whole", "killed"))
    for sa, sb in zip(a.segments, b.segments):
        for name, arr in sa.arrays().items():
            np.testing.assert_array_equal(arr, getattr(sb, name), err_msg=name)


def test_an_unreadable_predecessor_checkpoint_is_a_segment_error(tmp_path):
    """A broken checkpoint of the segment before stops the run with its name (stg-train: exit 2)."""
    from stg_train.segments import SegmentError, Span
    from stg_train.warm import warm_start

    broken = tmp_path / "checkpoint.pt"
    broken.write_bytes(b"not a checkpoint")
    with pytest.raises(SegmentError, match="checkpoint.pt: not a readable checkpoint.*warm start needs it"):
        warm_start(broken, Span(0, 0, 10), Span(1, 10, 10), (0, 0))
