"""The four extension points of docs/extending.md, each exercised by a toy extension: a dataset layout, a
splatter backend, a strategy and an stg-convert subcommand. Each toy is registered for its test only by
a fixture (monkeypatch undoes it, nothing leaks into other tests); each test checks what the rest of the
system then does with it. A new extension copies its recipe's test and drops the fixture (its
registration line is in the source then)."""
from __future__ import annotations

import sys
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_runtime import format as stg_format  # noqa: E402
from stg_runtime.atomic import write_atomic  # noqa: E402
from stg_runtime.camera import load_camera_path, save_camera_path  # noqa: E402
from stg_runtime.demo import demo_model  # noqa: E402
from stg_train import choices  # noqa: E402
from stg_train.cli import convert as convert_cli  # noqa: E402
from stg_train.data import DataError, detect_layout, load_dataset, load_n3v  # noqa: E402
from stg_train.data.frames import FrameSource, build_dataset, image_files  # noqa: E402
from stg_train.render import RenderOutput, rasterize, resolve_backend  # noqa: E402
from stg_train.render.torch_splat import rasterize_torch  # noqa: E402
from stg_train.strategy import Strategy, registry  # noqa: E402
from stg_train.synthetic import SyntheticScene  # noqa: E402
from stg_train.trainer import Trainer, TrainConfig  # noqa: E402

pytestmark = pytest.mark.usefixtures("two_torch_threads")

#: A short CPU run with nothing "auto" left to measure and no density control: only the toys act.
QUICK = dict(model="lite", iterations=3, batch=2, num_points=200, init="volume", depth_candidates=0,
             motion_init="zero", guided=False, appearance=False, pose_refine=False, lens_falloff=None,
             schedule={"refine_start": 10 ** 6, "reset_every": 0, "outside_at": 0}, splatter="torch")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A tiny N3V scene to train on: 3 cameras (cam00 held out), 2 frames, 32x24."""
    from stg_train.synthetic import write_n3v

    path = tmp_path_factory.mktemp("extending_scene")
    write_n3v(path, SyntheticScene(seed=0, duration=2 / 30), num_cameras=3, num_frames=2, fps=30.0, width=32, height=24)
    return load_n3v(path, prefer_png=True)


# -- 1. a dataset layout ---------------------------------------------------------------------------
def looks_like_toy(root: Path) -> bool:
    return (root / "toy.json").is_file() and (root / "images").is_dir()


def load_toy(root, downscale=1, cache_dir=None, num_frames=None, fps=None, progress=None, test_camera=None,
             lazy=False):
    """toy.json (a camera path, formats/stg-v1.md section 4) + images/<camera>/<frame>.png."""
    cameras = load_camera_path(root / "toy.json")
    sources = [FrameSource(images=image_files(root / "images" / c.name)) for c in cameras]
    return build_dataset(root, "toy", cameras, sources, test_camera=test_camera or cameras[0].name,
                         downscale=downscale, cache_dir=cache_dir, num_frames=num_frames, fps=fps, progress=progress,
                         lazy=lazy)


@pytest.fixture
def toy_layout(monkeypatch):
    monkeypatch.setitem(choices.LAYOUT_SPECS, "toy", (f"{__name__}:load_toy", f"{__name__}:looks_like_toy",
                                                      "toy.json and images/<camera>/<frame>.png"))


def _write_toy(root: Path):
    """A scene in the toy layout: 3 cameras x 2 frames, 32x24; returns (cameras, frames (C, F, H, W, 3))."""
    scene = SyntheticScene(seed=1, duration=2 / 30)
    cameras = scene.cameras(3, 32, 24)
    frames = np.stack([[np.rint(scene.render(c, k / 30) * 255).astype(np.uint8) for k in range(2)] for c in cameras])
    for c, cam in enumerate(cameras):
        (root / "images" / cam.name).mkdir(parents=True)
        for k in range(2):
            assert cv2.imwrite(str(root / "images" / cam.name / f"{k:04d}.png"), frames[c, k, ..., ::-1].copy())
    save_camera_path(root / "toy.json", cameras)
    return cameras, frames


def test_a_new_layout_is_detected_read_and_offered(toy_layout, tmp_path):
    root = tmp_path / "scene"
    cameras, frames = _write_toy(root)
    assert detect_layout(root) == "toy"
    data = load_dataset(root, cache_dir=tmp_path / "cache")
    assert [c.name for c in data.cameras] == [c.name for c in cameras] and data.test_cameras == [0]
    np.testing.assert_allclose(data.cameras[1].world_to_camera, cameras[1].world_to_camera)
    for c in range(3):
        for k in range(2):
            np.testing.assert_array_equal(data.frame(c, k), frames[c, k])
    half = load_dataset(root, layout="toy", downscale=2, cache_dir=tmp_path / "cache", test_camera=cameras[2].name)
    assert (half.cameras[0].width, half.cameras[0].fx) == (16, cameras[0].fx / 2) and half.test_cameras == [2]
    (tmp_path / "nothing").mkdir()
    with pytest.raises(DataError, match="toy:  *toy.json and images/<camera>/<frame>.png"):
        detect_layout(tmp_path / "nothing")  # what detection looked for names the new layout too
    from stg_train.cli import eval as eval_cli, train as train_cli

    args = train_cli.build_parser().parse_args([str(root), "--out", str(tmp_path / "run"), "--layout", "toy"])
    assert args.layout == "toy"
    assert eval_cli.build_parser().parse_args(["m.stg", str(root), "--layout", "toy"]).layout == "toy"


# -- 2. a splatter backend -------------------------------------------------------------------------
_DRAWN: list = []  # the toy's RenderOutputs (a fresh list per test: toy_splatter)


def rasterize_toy(means, quats, scales, opacities, features, camera) -> RenderOutput:
    """The torch splatter with other tiles: the same picture, drawn by another backend."""
    out = rasterize_torch(means, quats, scales, opacities, features, camera, tile_size=8)
    _DRAWN.append(out)
    return out


@pytest.fixture
def toy_splatter(monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "_DRAWN", [])
    monkeypatch.setitem(choices.SPLATTERS, "toy", f"{__name__}:rasterize_toy")


def test_a_new_splatter_is_chosen_by_name_and_draws_for_the_trainer(toy_splatter, dataset):
    assert resolve_backend("toy", "cpu") == "toy"
    trainer = Trainer(dataset, TrainConfig(**{**QUICK, "splatter": "toy"}))
    camera = dataset.cameras[1]
    g = trainer.params.at(0.5)
    got = rasterize(g.means, g.quats, g.scales, g.opacities, g.features, camera, backend="toy")
    want = rasterize(g.means, g.quats, g.scales, g.opacities, g.features, camera, backend="torch")
    assert got is _DRAWN[-1] and got.features.abs().max() > 0
    for name in ("features", "alpha", "depth", "radii"):  # the reference's picture (formats/stg-v1.md, section 3)
        torch.testing.assert_close(getattr(got, name), getattr(want, name))
    rgb, out = trainer.render(camera, 0.5)
    assert out is _DRAWN[-1]  # the trainer's picture is the toy's
    torch.testing.assert_close(rgb, trainer.params.colour(out.features, camera))
    drawn = len(_DRAWN)
    trainer.train_step()
    assert len(_DRAWN) == drawn + QUICK["batch"]  # every view of a training step
    from stg_train.cli import train as train_cli

    assert train_cli.build_parser().parse_args(["data/", "--out", "run/", "--splatter", "toy"]).splatter == "toy"


# -- 3. a strategy ---------------------------------------------------------------------------------
class FreezePositions(Strategy):
    """Drops the positions' gradient after backward(), so that training never moves a Gaussian; logs its calls."""

    def __init__(self, iterations: int):
        self.iterations, self.calls, self.restored = iterations, [], None

    def step_pre_backward(self, params, optimizer, step, context):
        self.calls.append(("pre", step, params.raw["xyz"].grad is None, len(context.renders)))

    def step_post_backward(self, params, optimizer, step, context):
        self.calls.append(("post", step, params.raw["xyz"].grad is None, len(context.renders)))
        params.raw["xyz"].grad.zero_()

    def state_dict(self):
        return {"calls": len(self.calls)}

    def load_state_dict(self, state):
        self.restored = state


@pytest.fixture
def toy_strategy(monkeypatch):
    monkeypatch.setitem(registry.STRATEGIES, "freeze", lambda setup: FreezePositions(setup.config.iterations))


def test_a_new_strategy_is_built_by_name_and_called_around_backward(toy_strategy, dataset, tmp_path):
    trainer = Trainer(dataset, TrainConfig(**QUICK, checkpoint_every=10), out_dir=tmp_path)
    toy = trainer.strategies[-1]
    assert isinstance(toy, FreezePositions) and toy.iterations == QUICK["iterations"]
    xyz, features = trainer.params["xyz"].detach().clone(), trainer.params["features"].detach().clone()
    trainer.train(progress=False)
    batch = QUICK["batch"]
    assert toy.calls == [c for s in (1, 2, 3) for c in (("pre", s, True, batch), ("post", s, False, batch))]
    assert torch.equal(trainer.params["xyz"], xyz)  # its edit acted on every step
    assert not torch.equal(trainer.params["features"], features)  # while the rest trained
    resumed = Trainer.resume(dataset, tmp_path / "checkpoint.pt")  # a checkpoint keeps its state_dict()
    assert isinstance(resumed.strategies[-1], FreezePositions) and resumed.strategies[-1].restored == {"calls": 6}


# -- 4. an stg-convert subcommand ------------------------------------------------------------------
def _add_count_arguments(parser):
    parser.add_argument("input", metavar="IN.stg")
    parser.add_argument("--out", metavar="TXT", help="write the counts there too")


def _run_count(args) -> int:
    counts = [s.count for s in stg_format.load(args.input).segments]
    if args.out:
        write_atomic(args.out, " ".join(map(str, counts)))
    print(f"{args.input}: {sum(counts)} Gaussians in {len(counts)} segment(s)")
    return 0


@pytest.fixture
def toy_command(monkeypatch):
    module = types.ModuleType("stg_toy_count", "count the Gaussians of a model, per segment\n\nPrints the total.")
    module.add_arguments, module.run = _add_count_arguments, _run_count
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setitem(convert_cli.COMMANDS, "count", module.__name__)


def test_a_new_convert_subcommand_parses_and_runs(toy_command, tmp_path, capsys):
    model = demo_model("lite", num_frames=2)
    stg_format.save(model, tmp_path / "m.stg")
    parser = convert_cli.build_parser()
    args = parser.parse_args(["count", str(tmp_path / "m.stg"), "--out", str(tmp_path / "n.txt")])
    assert (args.command, args.input) == ("count", str(tmp_path / "m.stg"))
    with pytest.raises(SystemExit) as e:
        parser.parse_args(["--help"])
    assert e.value.code == 0 and "count the Gaussians of a model, per segment" in capsys.readouterr().out
    assert convert_cli.main(["count", str(tmp_path / "m.stg"), "--out", str(tmp_path / "n.txt")]) == 0
    counts = [s.count for s in model.segments]
    assert (tmp_path / "n.txt").read_text() == " ".join(map(str, counts))
    assert f"{sum(counts)} Gaussians" in capsys.readouterr().out
    assert convert_cli.main(["count", str(tmp_path / "missing.stg")]) == 2  # main's errors apply to it too
    assert capsys.readouterr().err.startswith("stg-convert: error:")
