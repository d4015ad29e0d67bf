"""The web player's .stg reader (stg_runtime/web/stg-format.js, onnx-mlp.js) against the Python reader, run
in node: every test vector decodes to the same float32 arrays, decoder layers and cameras; every
malicious fixture is refused for the reason tests/runtime/malicious/index.json names (or loads where the
Python reader loads it); fuzzed files the Python reader refuses are refused. The same reader runs in the
page (tests/web/test_page.py shows the messages there)."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stg_runtime import FormatError
from stg_runtime import format as stg_format
from stg_runtime.onnx_mlp import read_mlp

NODE = shutil.which("node")
pytestmark = pytest.mark.skipif(NODE is None, reason="needs node (the reader's unit tests run in node 18+)")

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
VECTORS = sorted((ROOT / "formats" / "vectors").glob("*.stg"))
MALICIOUS = ROOT / "tests" / "runtime" / "malicious"


def read_with_js(path: Path, out: Path) -> dict:
    subprocess.run([NODE, str(HERE / "read_stg.mjs"), str(path), str(out)], check=True, timeout=60)
    return json.loads((out / "meta.json").read_text())


@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_vectors_decode_as_in_python(path, tmp_path):
    meta = read_with_js(path, tmp_path)
    assert "error" not in meta, meta
    model = stg_format.load(path)
    assert (meta["kind"], meta["fps"], meta["num_frames"]) == (model.kind, model.fps, model.num_frames)
    assert len(meta["cameras"]) == len(model.cameras)
    for js, cam in zip(meta["cameras"], model.cameras):
        assert (js["width"], js["height"], js["model"]) == (cam.width, cam.height, cam.model)
        np.testing.assert_array_equal(js["worldToCamera"], cam.world_to_camera.ravel())
        np.testing.assert_array_equal([js["fx"], js["fy"], js["cx"], js["cy"]], [cam.fx, cam.fy, cam.cx, cam.cy])
    assert len(meta["segments"]) == len(model.segments)
    for i, (js, seg) in enumerate(zip(meta["segments"], model.segments)):
        assert (js["start_frame"], js["num_frames"], js["count"]) == (seg.start_frame, seg.num_frames, seg.count)
        assert (tuple(js["context_frames"]), js["crossfade_frames"]) == (seg.context_frames, seg.crossfade_frames)
        for name, values in seg.arrays().items():
            got = np.fromfile(tmp_path / f"seg{i}_{name}.f32", "<f4")
            np.testing.assert_array_equal(got, values.ravel(), err_msg=f"segment {i}, {name}")
        if seg.decoder is None:
            assert js["layers"] is None
            continue
        mlp = read_mlp(seg.decoder)
        assert js["activation"] == seg.activation
        assert [tuple(layer) for layer in js["layers"]] == [(*w.shape, b is not None)
                                                            for w, b in zip(mlp.weights, mlp.biases)]
        for k, (w, b) in enumerate(zip(mlp.weights, mlp.biases)):
            np.testing.assert_array_equal(np.fromfile(tmp_path / f"seg{i}_w{k}.f32", "<f4"), w.ravel())
            if b is not None:
                np.testing.assert_array_equal(np.fromfile(tmp_path / f"seg{i}_b{k}.f32", "<f4"), b)


def test_segments_at_as_in_python(tmp_path):
    """segmentsAt (the segments and weights the page shows at t) against Model.segments_at: the
    crossfade vector, and three segments of 5, 3 and 6 frames with fades of 1, 3 and 3 frames (the
    middle one faded in and out over all of it), at every half frame and between."""
    from dataclasses import replace

    from stg_runtime.model import Model
    vector = stg_format.load(ROOT / "formats" / "vectors" / "full_crossfade.stg")
    lite = stg_format.load(ROOT / "formats" / "vectors" / "lite.stg").segments[0]
    for b1, b2 in ((1, 3), (3, 3)):
        segments = [replace(lite, start_frame=0, num_frames=5),
                    replace(lite, start_frame=5, num_frames=3, crossfade_frames=b1),
                    replace(lite, start_frame=8, num_frames=6, crossfade_frames=b2)]
        stg_format.save(Model("lite", 7.0, segments), tmp_path / f"three_{b1}_{b2}.stg")
    models = {"vector.stg": vector, **{p.name: stg_format.load(p) for p in sorted(tmp_path.glob("three_*.stg"))}}
    shutil.copy(ROOT / "formats" / "vectors" / "full_crossfade.stg", tmp_path / "vector.stg")
    reader = json.dumps((ROOT / "stg_runtime" / "web" / "stg-format.js").as_uri())
    script = ("import { readFileSync } from 'node:fs';"
              f"import {{ readStg, segmentsAt }} from {reader};"
              "const [file, ...times] = process.argv.slice(1);"
              "const model = await readStg(new Uint8Array(readFileSync(file)), file);"
              "console.log(JSON.stringify(times.map((t) => segmentsAt(model, Number(t)))));")
    for name, model in models.items():
        times = sorted({k / (4 * model.fps) for k in range(4 * model.num_frames + 1)} | {0.3, 0.45, 0.62, 0.95})
        times = [t for t in times if t <= model.duration]
        out = subprocess.run([NODE, "--input-type=module", "-e", script, str(tmp_path / name), *map(repr, times)],
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        crossfades = 0
        for t, parts in zip(times, json.loads(out.stdout)):
            index = {id(seg): k for k, seg in enumerate(model.segments)}
            want = [(index[id(seg)], tau, w) for seg, tau, w in model.segments_at(t)]
            got = [(p["index"], p["tau"], p["weight"]) for p in parts]
            assert [g[0] for g in got] == [w[0] for w in want], (name, t, got, want)
            np.testing.assert_allclose([g[1:] for g in got], [w[1:] for w in want], rtol=0, atol=1e-12,
                                       err_msg=f"{name}, t = {t}")
            crossfades += len(got) == 2
        assert crossfades >= 4, (name, crossfades)


def read_many(paths) -> dict[str, dict]:
    out = subprocess.run([NODE, str(HERE / "read_many.mjs"), *map(str, paths)], capture_output=True, text=True,
                         timeout=300, check=True)
    return {Path(r["file"]).name: r for r in map(json.loads, out.stdout.splitlines())}


def test_malicious_files_are_refused_for_the_python_reason():
    index = json.loads((MALICIOUS / "index.json").read_text())
    results = read_many(sorted(MALICIOUS.glob("*.stg")))
    assert sorted(results) == sorted(index)
    for name, expect in index.items():
        got = results[name]
        if expect["expect"] == "loads":
            assert got["ok"], got
            continue
        assert not got["ok"] and got["type"] == "FormatError", got
        assert got["error"].startswith(name + ": ") and re.search(expect["match"], got["error"]), got


def test_damaged_files_are_refused(tmp_path):
    data = (ROOT / "formats" / "vectors" / "full.stg").read_bytes()
    cases = {"cut.stg": data[:-100], "flipped.stg": data[:300] + bytes([data[300] ^ 1]) + data[301:],
             "empty.stg": b"", "magic.stg": b"PK" + data[2:], "version.stg": data[:8] + b"\x02\x00" + data[10:]}
    for name, payload in cases.items():
        (tmp_path / name).write_bytes(payload)
    results = read_many(sorted(tmp_path.glob("*.stg")))
    for name in cases:
        with pytest.raises(FormatError) as info:
            stg_format.load(tmp_path / name)
        python = str(info.value).split(": ", 1)[1]
        assert not results[name]["ok"] and results[name]["error"] == f"{name}: {python}", (results[name], python)


def test_fuzzed_files_refused_by_python_are_refused(tmp_path):
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from fuzz import mutate_stg
    finally:
        sys.path.remove(str(ROOT / "tools"))
    rng = np.random.default_rng(11)
    bases = [p.read_bytes() for p in VECTORS]
    expected = {}
    for k in range(300):
        how, data = mutate_stg(bases[k % len(bases)], rng)
        path = tmp_path / f"f{k:03d}.stg"
        path.write_bytes(data)
        try:
            stg_format.load(path)
            expected[path.name] = None
        except FormatError as e:
            expected[path.name] = str(e)
    results = read_many(sorted(tmp_path.glob("*.stg")))
    refused = [n for n, e in expected.items() if e is not None]
    assert len(refused) > 100
    for name in refused:
        assert not results[name]["ok"] and results[name]["type"] == "FormatError", (name, expected[name], results[name])
        assert results[name]["error"].startswith(name + ": ")
    accepted = [n for n, e in expected.items() if e is None]
    # the one known difference: JSON's NaN / Infinity literals, which Python's json reads and JSON.parse refuses
    differ = [n for n in accepted if not results[n]["ok"] and "JSON" not in results[n]["error"]]
    assert not differ, [results[n] for n in differ]


def test_player_modules_load_and_are_all_exported():
    """Every module but the page's app.js imports in node (no syntax error, no missing import), and
    stg-convert export-web copies every file of the player."""
    from stg_runtime.web.export import PLAYER_FILES
    web = ROOT / "stg_runtime" / "web"
    assert sorted(PLAYER_FILES) == sorted(p.name for p in web.iterdir() if p.suffix in (".js", ".html"))
    modules = [name for name in PLAYER_FILES if name.endswith(".js") and name not in ("app.js", "sort-worker.js")]
    script = "".join(f"await import({json.dumps((web / name).as_uri())});" for name in modules)
    out = subprocess.run([NODE, "--input-type=module", "-e", script], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
