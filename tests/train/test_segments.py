"""Long videos (CPU): a two-segment sequence trained into one file plays across the boundary from the
right segment at the right normalised time; segments trained separately (`--segments`) merge into the
same file; a run killed inside a segment resumes there, keeping the finished ones; merge errors."""
from __future__ import annotations

import copy
import json
import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_runtime import format as stg_format  # noqa: E402
from stg_runtime.format import FormatError  # noqa: E402
from stg_runtime.player import Player  # noqa: E402
from stg_train.cli.eval import main as eval_main  # noqa: E402
from stg_train.cli.train import main as train_main  # noqa: E402
from stg_train.convert.merge import attribute_encodings, merge_files, merge_models  # noqa: E402
from stg_train.data import load_n3v  # noqa: E402
from stg_train.export import GoldenDiff, trainer_render  # noqa: E402
from stg_train.params import STGParams  # noqa: E402
from stg_train.segments import parse_segment_list, plan_segments  # noqa: E402
from stg_train.trainer import Trainer  # noqa: E402

# 8 frames over 2 s: the sphere moves and the box turns visibly between the two 4-frame segments.
SCENE = dict(num_cameras=4, num_frames=8, fps=4.0, width=64, height=48)
ARGS = ["--segment-frames", "4", "--iterations", "10", "--points", "200", "--init", "volume",
        "--checkpoint-every", "5", "--segment-context", "0", "--quiet"]  # hard cuts (context_run: with context)


pytestmark = pytest.mark.usefixtures("two_torch_threads")


@pytest.fixture(scope="module")
def scene_dir(synthetic_n3v):
    return synthetic_n3v("seg_scene", **SCENE)


@pytest.fixture(scope="module")
def dataset(scene_dir):
    return load_n3v(scene_dir, prefer_png=True)


@pytest.fixture(scope="module")
def full_run(scene_dir, tmp_path_factory):
    """Both segments trained in one run: OUT."""
    out = tmp_path_factory.mktemp("seg_runs") / "all"
    assert train_main([str(scene_dir), "--out", str(out)] + ARGS) == 0
    return out


def _params(out, index: int) -> STGParams:
    state = torch.load(out / "segments" / f"{index:02d}" / "checkpoint.pt", map_location="cpu", weights_only=True)
    return STGParams.from_state_dict(state["params"], "cpu")


def _assert_same_segments(a, b) -> None:
    assert len(a.segments) == len(b.segments)
    for sa, sb in zip(a.segments, b.segments):
        assert (sa.start_frame, sa.num_frames, sa.decoder) == (sb.start_frame, sb.num_frames, sb.decoder)
        for name, arr in sa.arrays().items():
            np.testing.assert_array_equal(arr, getattr(sb, name), err_msg=name)


# -- the plan and the dataset view -------------------------------------------------------------------
def test_plan_and_segment_list():
    assert plan_segments(8, 4) == [(0, 0, 4), (1, 4, 4)]
    assert plan_segments(9, 4) == [(0, 0, 4), (1, 4, 5)]            # a 1-frame tail joins segment 1
    assert plan_segments(10, 4) == [(0, 0, 4), (1, 4, 4), (2, 8, 2)]  # half a segment stays on its own
    assert plan_segments(30, 50) == [(0, 0, 30)]
    assert plan_segments(310, 50)[-1] == (5, 250, 60)
    assert parse_segment_list("2,3") == [2, 3] and parse_segment_list("0-2,5,1") == [0, 1, 2, 5]
    for bad in ("x", "2-1", "1-", ""):
        with pytest.raises(ValueError, match="segment list"):
            parse_segment_list(bad)


def test_frame_range_view_shares_frames(dataset):
    view = dataset.frame_range(4, 4)
    assert view.num_frames == 4 and view.start_frame == 4 and np.shares_memory(view.frames, dataset.frames)
    np.testing.assert_array_equal(view.frame(1, 0), dataset.frame(1, 4))
    np.testing.assert_allclose(view.frame_times, np.arange(4, 8) / SCENE["fps"])
    assert view.frame_range(1, 2).start_frame == 5
    with pytest.raises(IndexError):
        dataset.frame_range(6, 4)


# -- one run, two segments, one file -----------------------------------------------------------------
def test_two_segments_in_one_file(full_run):
    player = Player(full_run / "model.stg", device="cpu")
    assert [(s.start_frame, s.num_frames) for s in player.model.segments] == [(0, 4), (4, 4)]
    assert player.num_frames == 8 and player.fps == SCENE["fps"] and player.duration == 2.0
    for k in (0, 1):
        folder = full_run / "segments" / f"{k:02d}"
        assert {"checkpoint.pt", "model.stg", "metrics.json"} <= {p.name for p in folder.iterdir()}
        alone = stg_format.load(folder / "model.stg")
        assert (alone.start_frame, alone.num_frames) == (4 * k, 4)
    metrics = json.loads((full_run / "metrics.json").read_text())
    assert metrics["missing_segments"] == [] and metrics["heldout"]["images"] == 8  # cam00 x all 8 frames
    assert [s["start_frame"] for s in metrics["segments"]] == [0, 4]
    assert all(s["export_check"]["max_abs"] <= 2e-2 for s in metrics["segments"])  # golden check per segment
    assert player.model.provenance["tool"] == "stg-train"
    assert [s["start_frame"] for s in player.model.provenance["sources"]] == [0, 4]


def test_playback_across_the_boundary(full_run, dataset):
    player = Player(full_run / "model.stg", device="cpu")
    cam = dataset.cameras[dataset.test_cameras[0]]
    params = [_params(full_run, 0), _params(full_run, 1)]
    for frame in (3, 4):  # the last frame of segment 0, the first of segment 1
        k, j = divmod(frame, 4)
        merged = player.render_frame(cam, frame)
        alone = Player(full_run / "segments" / f"{k:02d}" / "model.stg", device="cpu").render_frame(cam, frame)
        np.testing.assert_array_equal(merged, alone)
        # the trainer's own render of segment k at tau = j / 4 ...
        assert GoldenDiff.of(merged, trainer_render(params[k], cam, j / 4)).ok
        # ... and not the other segment's, nor tau normalised over the whole video: most values of those
        # renders differ by more than the golden tolerance (1e-3)
        for wrong in (trainer_render(params[1 - k], cam, j / 4), trainer_render(params[k], cam, frame / 8)):
            diff = GoldenDiff.of(merged, wrong)
            assert diff.fraction_over > 0.2 and diff.max_abs > 5e-3, diff
        mse = np.mean((merged - dataset.image(dataset.test_cameras[0], frame)) ** 2)
        assert -10 * np.log10(mse) > 15  # a real image of the scene (10 steps: no quality claim)


def test_eval_on_multi_segment_and_single_segment_files(full_run, scene_dir, tmp_path, capsys):
    metrics = json.loads((full_run / "metrics.json").read_text())
    assert eval_main([str(full_run / "model.stg"), str(scene_dir), "--json", str(tmp_path / "e.json"), "--quiet"]) == 0
    figures = json.loads((tmp_path / "e.json").read_text())
    assert figures["images"] == 8 and abs(figures["psnr"] - metrics["heldout"]["psnr"]) < 1e-6
    seams, rows = figures["seams"], {r["frame"]: r["psnr"] for r in figures["per_frame"]}  # one held-out camera
    assert sorted(seams["boundary"]) == ["0", "3", "4", "7"] and list(seams["seams"]) == ["4"]
    assert all(abs(seams["boundary"][k] - rows[int(k)]) < 1e-4 for k in seams["boundary"])
    interior = np.mean([rows[j] for j in (1, 2, 5, 6)])
    assert abs(figures["worst_boundary_dip"] - (interior - min(rows[j] for j in (0, 3, 4, 7)))) < 1e-4
    assert figures["seam_flicker_ratio"] > 0
    one = full_run / "segments" / "01" / "model.stg"
    assert eval_main([str(one), str(scene_dir), "--json", str(tmp_path / "s.json"), "--quiet"]) == 0
    single = json.loads((tmp_path / "s.json").read_text())
    assert [r["frame"] for r in single["per_frame"]] == [4, 5, 6, 7]
    assert single["seams"] is None and "seam_flicker_ratio" not in single  # one segment: no seam
    assert "covers frames 4-7" in capsys.readouterr().err


# -- segments trained separately, then merged ------------------------------------------------------
def test_segments_trained_separately_merge_to_the_same_file(full_run, scene_dir, tmp_path, capsys):
    out = tmp_path / "par"
    assert train_main([str(scene_dir), "--out", str(out), "--segments", "1"] + ARGS) == 0
    err = capsys.readouterr().err
    assert not (out / "model.stg").exists()
    assert "segment 0 (frames 0-3)" in err and "--segments 0" in err and "stg-convert merge" in err
    partial = json.loads((out / "metrics.json").read_text())
    assert partial["missing_segments"] == [0] and partial["heldout"]["images"] == 4
    assert train_main([str(scene_dir), "--out", str(out), "--segments", "0"] + ARGS) == 0
    everything = stg_format.load(full_run / "model.stg")
    _assert_same_segments(stg_format.load(out / "model.stg"), everything)
    # by hand, in any order of inputs
    seg = out / "segments"
    merged = merge_files([seg / "01" / "model.stg", seg / "00" / "model.stg"], tmp_path / "m.stg")
    _assert_same_segments(merged, everything)
    _assert_same_segments(stg_format.load(tmp_path / "m.stg"), everything)


class _Killed(Exception):
    pass


def test_resume_continues_the_killed_segment_and_keeps_finished_ones(full_run, scene_dir, tmp_path, monkeypatch,
                                                                    capsys):
    out = tmp_path / "killed"
    step = Trainer.train_step

    def killed_in_segment_1(trainer):
        if trainer.dataset.start_frame == 4 and trainer.step == 7:  # two steps after the checkpoint at 5
            raise _Killed
        return step(trainer)

    monkeypatch.setattr(Trainer, "train_step", killed_in_segment_1)
    with pytest.raises(_Killed):
        train_main([str(scene_dir), "--out", str(out)] + ARGS)
    monkeypatch.undo()
    first = out / "segments" / "00" / "model.stg"
    assert (out / "segments" / "00" / "metrics.json").exists() and not (out / "segments" / "01" / "model.stg").exists()
    assert not (out / "model.stg").exists()
    stamp = first.stat().st_mtime_ns
    capsys.readouterr()
    assert train_main([str(scene_dir), "--out", str(out), "--resume"] + ARGS[:-1]) == 0
    err = capsys.readouterr().err
    assert "segment 0 (frames 0-3): finished" in err and "at step 5 of 10" in err
    assert first.stat().st_mtime_ns == stamp  # not retrained, not rewritten
    _assert_same_segments(stg_format.load(out / "model.stg"), stg_format.load(full_run / "model.stg"))


def test_cli_segment_errors(full_run, scene_dir, capsys):
    base = [str(scene_dir), "--out", str(full_run)]
    assert train_main(base + ["--segments", "2"] + ARGS) == 2
    err = capsys.readouterr().err
    assert "--segments 2" in err and "2 segments" in err and "Traceback" not in err
    assert train_main(base + ["--segment-frames", "3"] + ARGS[2:]) == 2  # OUT was cut every 4 frames
    assert "plan.json" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        train_main(base + ["--segments", "3-1"] + ARGS)
    assert e.value.code == 2 and "backwards" in capsys.readouterr().err


# -- merge ---------------------------------------------------------------------------------------------
def test_merge_errors_name_inputs_and_frames(full_run, tmp_path):
    a = stg_format.load(full_run / "segments" / "00" / "model.stg")
    b = stg_format.load(full_run / "segments" / "01" / "model.stg")
    names = ["A.stg", "B.stg"]

    def moved(model, start):
        m = copy.deepcopy(model)
        m.segments[0].start_frame = start
        return m

    with pytest.raises(ValueError, match=r"gap: frames 4-5 are in no input \(between A.stg, frames 0-3, and B.stg"):
        merge_models([a, moved(b, 6)], names)
    with pytest.raises(ValueError, match=r"A.stg \(frames 0-3\) and B.stg \(frames 2-5\) overlap at frames 2-3"):
        merge_models([a, moved(b, 2)], names)
    lite = copy.deepcopy(b)
    lite.kind, lite.segments[0].features, lite.segments[0].decoder = "lite", lite.segments[0].features[:, :3], None
    with pytest.raises(ValueError, match="kind mismatch: A.stg is a full model, B.stg is lite"):
        merge_models([a, lite], names)
    faster = copy.deepcopy(b)
    faster.fps = 8.0
    with pytest.raises(ValueError, match="fps mismatch"):
        merge_models([a, faster], names)
    # files: a damaged input is named, nothing is written
    bad = tmp_path / "bad.stg"
    bad.write_bytes((full_run / "segments" / "01" / "model.stg").read_bytes()[:-10])
    with pytest.raises(FormatError, match="bad.stg"):
        merge_files([full_run / "segments" / "00" / "model.stg", bad], tmp_path / "out.stg")
    with pytest.raises(ValueError, match="missing.stg: cannot read"):
        merge_files([tmp_path / "missing.stg"], tmp_path / "out.stg")
    assert not list(tmp_path.glob("out.stg*"))


def test_merge_keeps_encodings_and_unites_metadata(full_run, tmp_path):
    a = stg_format.load(full_run / "segments" / "00" / "model.stg")
    b = stg_format.load(full_run / "segments" / "01" / "model.stg")
    b.bounds = ((-9.0, 0.0, 0.0), (0.0, 0.0, 99.0))
    stg_format.save(a, tmp_path / "a.stg", encodings={"position": "f16", "features": "u8", "opacity": "u8"})
    stg_format.save(b, tmp_path / "b.stg", encodings={"position": "f16", "features": "u8", "opacity": "u16"})
    merged = merge_files([tmp_path / "b.stg", tmp_path / "a.stg"], tmp_path / "m.stg")
    used = attribute_encodings(tmp_path / "m.stg")
    assert used["position"] == {"f16"} and used["features"] == {"u8"} and used["opacity"] == {"f32"}
    back = stg_format.load(tmp_path / "m.stg")
    for source, seg in zip((tmp_path / "a.stg", tmp_path / "b.stg"), back.segments):
        original = stg_format.load(source).segments[0]
        np.testing.assert_array_equal(seg.position, original.position)  # f16 again: exact
        step = np.ptp(original.features, axis=0) / 255
        assert np.all(np.abs(seg.features - original.features) <= 0.02 * step + 1e-7)  # u8 re-encoded
    lo, hi = np.asarray(back.bounds)
    assert lo[0] == -9.0 and hi[2] == 99.0 and np.all(lo <= np.asarray(a.bounds[0]))
    assert [s["name"] for s in merged.provenance["sources"]] == [str(tmp_path / "a.stg"), str(tmp_path / "b.stg")]
    assert len(back.cameras) == len(a.cameras)  # the same rig, not listed twice


def test_merge_needs_no_torch(full_run, tmp_path):
    import subprocess
    import sys

    code = ("import sys\n"
            "class Block:\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name == 'torch' or name.startswith('torch.'):\n"
            "            raise ImportError(name + ' is blocked')\n"
            "sys.meta_path.insert(0, Block())\n"
            "from stg_train.convert.merge import merge_files\n"
            "m = merge_files(sys.argv[1:3], sys.argv[3])\n"
            "assert 'torch' not in sys.modules and len(m.segments) == 2\n")
    seg = full_run / "segments"
    args = [str(seg / "01" / "model.stg"), str(seg / "00" / "model.stg"), str(tmp_path / "m.stg")]
    run = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    _assert_same_segments(stg_format.load(tmp_path / "m.stg"), stg_format.load(full_run / "model.stg"))


# -- context frames and crossfades (format 1.3) ----------------------------------------------------
def test_frame_range_with_context_and_the_chunks(dataset):
    from stg_train.segments import Span, cache_chunks, context_of, segment_view

    view = dataset.frame_range(4, 2, context=(2, 1))
    assert (view.start_frame, view.num_frames, view.context_frames) == (2, 5, (2, 1))
    np.testing.assert_array_equal(view.frame(0, 0), dataset.frame(0, 2))
    shown = view.shown()
    assert (shown.start_frame, shown.num_frames, shown.context_frames) == (4, 2, (0, 0))
    with pytest.raises(IndexError, match="frames -1..5"):
        dataset.frame_range(1, 2, context=(2, 3))
    plan = plan_segments(8, 4)
    assert [context_of(s, 8, 2) for s in plan] == [(0, 2), (2, 0)]
    assert context_of(Span(1, 4, 2), 7, 5) == (4, 1)  # no more than the video has
    assert segment_view(dataset, plan[1], 2).start_frame == 2
    # each segment's edge frames are their own chunks: a view with context opens the neighbour's small one
    assert cache_chunks(plan_segments(30, 10), 2) == [(0, 2), (2, 6), (8, 2), (10, 2), (12, 6), (18, 2), (20, 2),
                                                      (22, 6), (28, 2)]
    assert cache_chunks(plan, 0) == [(0, 4), (4, 4)]


def test_frame_weights_and_steps(dataset):
    from stg_train.trainer import EDGE_FRAMES, END_FRAME_FACTOR, frame_time, frame_weights, run_steps

    assert run_steps(100, dataset) == 100 and run_steps(100, dataset.frame_range(2, 4, context=(2, 2))) == 200
    # time counts over the shown frames: a segment's axis is the same with context or without
    assert [frame_time(dataset, j) for j in (0, 4)] == [0.0, 4 / dataset.num_frames]
    view = dataset.frame_range(2, 4, context=(2, 1))
    assert [frame_time(view, j) for j in range(7)] == [-0.5, -0.25, 0.0, 0.25, 0.5, 0.75, 1.0]

    assert frame_weights(10, (0, 0), 1.0) is None and frame_weights(10, (2, 2), 1.0) is None  # uniform
    p = frame_weights(12, (2, 0), 3.0)  # the shown frames' ends drawn 3 times as often, the context's not
    assert p.sum() == pytest.approx(1.0)
    weight = p / p[6]
    # the video's last frame (no context after it) END_FRAME_FACTOR times that again; the first shown
    # frame is next to a seam (context before it): no more than its edge neighbours
    assert weight[-1] == pytest.approx(3.0 * END_FRAME_FACTOR) and np.allclose(weight[-EDGE_FRAMES:-1], 3.0)
    assert np.allclose(weight[2:2 + EDGE_FRAMES], 3.0)
    assert np.allclose(weight[:2], 1.0) and np.allclose(weight[2 + EDGE_FRAMES:-EDGE_FRAMES], 1.0)
    weight = frame_weights(14, (4, 4), 3.0) / frame_weights(14, (4, 4), 3.0)[0]  # 6 shown frames, 3 at each end
    assert np.allclose(weight, [1] * 4 + [3] * 6 + [1] * 4)


def test_edge_weight_default_and_option():
    from stg_train.cli.train import _config, build_parser
    from stg_train.trainer import EDGE_FRAMES, TrainConfig, frame_weights

    assert TrainConfig().edge_weight == 3.0  # the video's ends drawn 3 times as often (docs/training.md, "Seams")
    p = frame_weights(30, (0, 0), TrainConfig().edge_weight) / frame_weights(30, (0, 0), TrainConfig().edge_weight)[15]
    assert np.allclose(p[1:EDGE_FRAMES], 3.0) and np.allclose(p[-EDGE_FRAMES:-1], 3.0)
    assert p[0] == p[-1] == pytest.approx(6.0)  # the video's own first and last frames twice that
    args = build_parser().parse_args(["data", "--out", "run", "--edge-weight", "2"])
    assert _config(args, "numba").edge_weight == 2.0
    assert _config(build_parser().parse_args(["data", "--out", "run", "--edge-weight", "1"]), "numba").edge_weight == 1.0


def test_a_context_checkpoint_of_the_earlier_time_axis_is_refused(context_run, dataset, scene_dir, tmp_path, capsys):
    """Before the time axis counted over the shown frames, a segment's spanned its context frames too: such a
    checkpoint would resume on another axis, so it is refused with what to do."""
    state = torch.load(context_run / "segments" / "00" / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert state["time"] == "shown"
    del state["time"]
    torch.save(state, tmp_path / "checkpoint.pt")
    with pytest.raises(ValueError, match="earlier version.*remove its folder"):
        Trainer.resume(dataset.frame_range(0, 4, context=(0, 2)), tmp_path / "checkpoint.pt")
    # and stg-train --resume says so, with exit code 2 and no traceback
    run = tmp_path / "run"
    shutil.copytree(context_run, run)
    (run / "model.stg").unlink()
    (run / "segments" / "00" / "metrics.json").unlink()
    torch.save(state, run / "segments" / "00" / "checkpoint.pt")
    assert train_main([str(scene_dir), "--out", str(run), "--resume"] + ARGS + ["--segment-context", "2"]) == 2
    assert "earlier version" in capsys.readouterr().err


@pytest.fixture(scope="module")
def context_run(scene_dir, tmp_path_factory):
    """Both segments trained with 2 context frames: each fitted to frames 0-5 and 2-7."""
    out = tmp_path_factory.mktemp("seg_context") / "ctx"
    assert train_main([str(scene_dir), "--out", str(out)] + ARGS + ["--segment-context", "2"]) == 0
    return out


def test_context_segments_crossfade_over_the_seam(context_run, dataset):
    model = stg_format.load(context_run / "model.stg")
    assert [(s.start_frame, s.num_frames, s.context_frames, s.crossfade_frames) for s in model.segments] == \
        [(0, 4, (0, 2), 0), (4, 4, (2, 0), 2)]
    for k in (0, 1):  # each segment's own file is a valid model of its own frames
        alone = stg_format.load(context_run / "segments" / f"{k:02d}" / "model.stg")
        assert (alone.start_frame, alone.num_frames, alone.segments[0].context_frames) == (4 * k, 4, model.segments[k].context_frames)
    metrics = json.loads((context_run / "metrics.json").read_text())
    assert metrics["heldout"]["images"] == 8 and all(s["export_check"]["max_abs"] <= 2e-2 for s in metrics["segments"])
    assert [s["iterations"] for s in metrics["segments"]] == [15, 15]  # 10 x 6 frames / 4 shown (trainer.run_steps)
    player = Player(context_run / "model.stg", device="cpu")
    cam = dataset.cameras[dataset.test_cameras[0]]
    a, b = _params(context_run, 0), _params(context_run, 1)  # trained over frames 0-5 and 2-7 (6 frames each)
    # each one's time is normalised over its 4 shown frames (0-3, 4-7), its context frames just outside [0, 1):
    # frames 3 and 4 blend segment 0 at tau 3/4, 4/4 and segment 1 at tau -1/4, 0
    for frame, w in ((3, 0.25), (4, 0.75)):
        want = (1 - w) * trainer_render(a, cam, frame / 4) + w * trainer_render(b, cam, (frame - 4) / 4)
        assert GoldenDiff.of(player.render_frame(cam, frame), want.astype(np.float32)).ok
    assert GoldenDiff.of(player.render_frame(cam, 2), trainer_render(a, cam, 2 / 4)).ok  # outside: one segment
    assert GoldenDiff.of(player.render_frame(cam, 5), trainer_render(b, cam, 1 / 4)).ok
    # merge: the crossfade follows the context, and can be shortened or cut
    files = [context_run / "segments" / f"{k:02d}" / "model.stg" for k in (0, 1)]
    models = [stg_format.load(f) for f in files]
    assert [s.crossfade_frames for s in merge_models(models).segments] == [0, 2]
    assert [s.crossfade_frames for s in merge_models(models, crossfade=0).segments] == [0, 0]
    assert [s.crossfade_frames for s in merge_models(models, crossfade=9).segments] == [0, 4]  # 2 x the context


def test_merge_cli_crossfade(context_run, tmp_path, capsys):
    from stg_train.cli.convert import main as convert_main

    files = [str(context_run / "segments" / f"{k:02d}" / "model.stg") for k in (0, 1)]
    assert convert_main(["merge", *files, str(tmp_path / "m.stg"), "--crossfade", "4"]) == 0
    assert "crossfades [4] frames" in capsys.readouterr().out
    assert stg_format.load(tmp_path / "m.stg").segments[1].crossfade_frames == 4
    assert convert_main(["merge", *files, str(tmp_path / "cut.stg"), "--crossfade", "0"]) == 0
    assert "crossfades" not in capsys.readouterr().out
