"""Hostile .stg files (tests/runtime/malicious/, made by tools/make_malicious_files.py): each is refused
with FormatError for the reason index.json names, or loads and renders a finite image. Also: the
documented way to open an honest model beyond the default limits, and RenderError."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from stg_runtime import FormatError, Limits, Player, RenderError
from stg_runtime import format as stg_format
from stg_runtime.cli import main as render_main
from stg_runtime.demo import demo_model

FOLDER = Path(__file__).resolve().parent / "malicious"
INDEX = json.loads((FOLDER / "index.json").read_text())


def test_every_fixture_is_listed():
    assert sorted(INDEX) == sorted(p.name for p in FOLDER.glob("*.stg"))


@pytest.mark.parametrize("name", sorted(INDEX))
def test_hostile_file(name):
    expect = INDEX[name]
    path = FOLDER / name
    if expect["expect"] == "refused":
        with pytest.raises(FormatError) as info:
            stg_format.load(path)
        message = str(info.value)
        assert message.startswith(str(path)) and re.search(expect["match"], message), message
        return
    player = Player(path, device="cpu")
    image = player.render(player.cameras[0], 0.1)
    assert image.shape == (32, 48, 3) and np.all(np.isfinite(image)) and image.max() > 0


def test_the_zlib_bomb_is_an_honest_model_beyond_the_default_limits():
    path = FOLDER / "zlib_bomb.stg"
    model = stg_format.load(path, limits=Limits(max_expansion=2000))
    assert model.segments[0].count == 1 << 20
    with pytest.raises(FormatError, match="would take"):
        Player(path, device="cpu")
    with pytest.raises(FormatError, match="Gaussians, more than the reader's limit of 1000"):
        Player(path, device="cpu", limits=Limits(max_gaussians=1000, max_expansion=2000))


def test_stg_render_refuses_each_refused_file_in_one_line(tmp_path, capsys):
    for name, expect in INDEX.items():
        if expect["expect"] != "refused":
            continue
        assert render_main([str(FOLDER / name), "--out", str(tmp_path / "frames"), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"stg-render: error: {FOLDER / name}: ") and err.count("\n") == 1, err
    assert not (tmp_path / "frames").exists()


class _Broken:
    """A stand-in onnxruntime session that fails as onnxruntime's errors do (not RuntimeError)."""

    def run(self, *args, **kwargs):
        from onnxruntime.capi.onnxruntime_pybind11_state import Fail
        raise Fail("[ONNXRuntimeError] : 1 : FAIL : injected")


def test_any_render_failure_is_a_render_error_naming_the_file(tmp_path, capsys):
    path = tmp_path / "scene.stg"
    stg_format.save(demo_model("full", num_frames=2), path)
    player = Player(path, device="cpu")
    camera = player.cameras[0].resized(16, 12)
    player.render(camera, 0.0)
    decoder = next(iter(player._decoders.values()))
    decoder.session = _Broken()
    with pytest.raises(RenderError, match=rf"^{re.escape(str(path))}: rendering t = 0.0 s failed \(Fail: "):
        player.render(camera, 0.0)
    with pytest.raises(ValueError, match="outside"):  # bad arguments stay ValueError
        player.render(camera, 99.0)


def test_a_non_finite_image_is_a_render_error(monkeypatch):
    import stg_runtime.player as player_module
    player = Player(demo_model("lite", num_frames=2), device="cpu")
    monkeypatch.setattr(player_module, "lite_colour", lambda f: np.full(f.shape[:2] + (3,), np.nan, np.float32))
    with pytest.raises(RenderError, match="^<model>: the image at t = 0.0 s has non-finite values"):
        player.render(player.cameras[0].resized(16, 12), 0.0)
