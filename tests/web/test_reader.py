"""The web player's .stg reader (stg_runtime/web/stg-format.js, onnx-mlp.js) against the Python reader, run
in node: every test vector decodes to the same float32 arrays, decoder layers and cameras; every
malicious fixture is refused for the reason tests/runtime/malicious/index.json names (or loads where the
Python reader loads it); fuzzed files the Python reader refuses are refused. The same reader runs in the
page (tests/web/test_page.py shows the messages there)."""
from __future__ import annotations

import importlib
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


def _from_tools(module: str, *names: str):
    """`names` of tools/`module`.py (one name: the object itself, else a tuple)."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        found = importlib.import_module(module)
    finally:
        sys.path.remove(str(ROOT / "tools"))
    values = tuple(getattr(found, name) for name in names)
    return values[0] if len(values) == 1 else values


def python_error(path: Path, named: str | None = None) -> str | None:
    """The Python reader's FormatError message for `path`, None if it loads. The message starts with
    the path, or with `named` in its place (the node scripts name files by their names)."""
    try:
        stg_format.load(path)
    except FormatError as e:
        return str(e) if named is None else f"{named}: {str(e).split(': ', 1)[1]}"
    return None


def read_with_js(path: Path, out: Path) -> dict:
    subprocess.run([NODE, str(HERE / "read_stg.mjs"), str(path), str(out)], check=True, timeout=60)
    return json.loads((out / "meta.json").read_text())


@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_vectors_decode_as_in_python(path, tmp_path):
    assert_reads_as_in_python(path, tmp_path)


def assert_reads_as_in_python(path: Path, tmp_path: Path) -> None:
    """The JS reader reads `path` to the float32 arrays, decoder layers and cameras of format.load."""
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


def test_web_preset_like_file_decodes_as_in_python(tmp_path):
    """(1.5) The encodings `stg-convert compress --preset web` chose for the demo model (acB and
    acB-delta in parts, B from 1 to 12), written on the demo model's 3775 Gaussians: the JS range
    decoder gives Python's float32 values bit for bit."""
    from stg_runtime.demo import demo_model
    web = {"opacity": "ac1-delta", "t_center": "u8", "t_scale": "ac1-delta",
           "position": "ac12-delta:3+ac8-delta:3+ac10-delta:3+ac8-delta:3", "rotation": "ac5:4+ac7:4",
           "scale": "ac7-delta", "features": "ac10-delta:3+ac6:3+ac4:3"}
    path = tmp_path / "web.stg"
    path.write_bytes(stg_format.dumps(demo_model("full", num_frames=4), web, codec="raw"))
    assert path.read_bytes()[8:12] == bytes([1, 0, 5, 0])  # version 1.5
    assert_reads_as_in_python(path, tmp_path / "out")


def test_every_ac_width_decodes_as_in_python(tmp_path):
    """(1.5) Every B from 1 to 16, as acB and acB-delta, as parts and as a codebook, on 4000 random
    Gaussians (an sh model of 48 feature channels, one of them constant): the same float32 values."""
    from stg_runtime import Model, Segment
    rng = np.random.default_rng(5)
    n = 4000
    features = rng.normal(0, 1, (n, 48)).astype(np.float32)
    features[:, 7] = 0.25  # a constant channel: scale 0
    segment = Segment(0, 6, opacity=rng.uniform(0, 1, n), t_center=np.sort(rng.uniform(0, 1, n)),
                      t_scale=rng.uniform(0.01, 2, n), position=rng.normal(0, 3, (n, 3, 3)),
                      rotation=rng.integers(-3, 4, (n, 2, 4)) / 3.0, scale=rng.uniform(-5, 0, (n, 3)),
                      features=features)
    model = Model("sh", 24.0, [segment])
    widths = "+".join(f"ac{b}{'-delta' if k % 2 else ''}:3" for k, b in enumerate(range(1, 17)))
    encodings = {"opacity": "ac16", "t_center": "ac16-delta", "t_scale": "ac3", "position": "ac13:4+ac2-delta:5",
                 "rotation": "vq/ac9-delta", "scale": "vq/ac1", "features": widths}
    for codec in ("raw", "zlib"):  # (acB blobs are raw either way; zlib for the vq indices)
        path = tmp_path / f"widths_{codec}.stg"
        path.write_bytes(stg_format.dumps(model, encodings, codec=codec))
        header = json.loads(path.read_bytes()[20:20 + int.from_bytes(path.read_bytes()[12:20], "little")])
        parts = header["segments"][0]["attributes"]["features"]["parts"]
        assert [p["encoding"] for p in parts][:3] == ["ac1", "ac2-delta", "ac3"] and len(parts) == 16
        assert_reads_as_in_python(path, tmp_path / codec)


def test_ac_decoder_reads_the_python_encoder(tmp_path):
    """(1.5) acDecode on streams of stg_runtime.range_coder.encode, every B from 1 to 16: uniform,
    constant, skewed (long runs of 0xFF bytes and carries in the encoder) and alternating symbols, 1 to
    5 channels, and no symbols at all (the 5 bytes of a flush): the symbols back, the bytes all read."""
    from stg_runtime import range_coder
    rng = np.random.default_rng(8)
    cases = []
    for bits in range(1, 17):
        top = 1 << bits
        for kind in ("uniform", "constant", "skewed", "alternating", "empty"):
            channels, count = int(rng.integers(1, 6)), 0 if kind == "empty" else int(rng.integers(1, 700))
            if kind == "uniform":
                symbols = rng.integers(0, top, (channels, count))
            elif kind == "constant":
                symbols = np.full((channels, count), top - 1)
            elif kind == "skewed":
                symbols = np.where(rng.random((channels, count)) < 0.97, 0, rng.integers(0, top, (channels, count)))
            else:
                symbols = np.tile([0, top - 1], (channels, count // 2 + 1))[:, :count]
            data = range_coder.encode(symbols, bits)
            (tmp_path / f"{len(cases)}.bin").write_bytes(data)
            cases.append((bits, channels, count, symbols.astype(np.uint16)))
    reader = json.dumps((ROOT / "stg_runtime" / "web" / "stg-format.js").as_uri())
    script = ("import { readFileSync, writeFileSync } from 'node:fs';"
              f"import {{ acDecode }} from {reader};"
              "const [dir, ...cases] = process.argv.slice(1);"
              "cases.forEach((c, k) => { const [bits, channels, count] = c.split(',').map(Number);"
              "  const out = acDecode(new Uint8Array(readFileSync(`${dir}/${k}.bin`)), channels, count, bits);"
              "  writeFileSync(`${dir}/${k}.u16`, Buffer.from(out.buffer)); });")
    out = subprocess.run([NODE, "--input-type=module", "-e", script, str(tmp_path),
                          *(f"{b},{c},{n}" for b, c, n, _ in cases)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    for k, (bits, channels, count, symbols) in enumerate(cases):
        got = np.fromfile(tmp_path / f"{k}.u16", "<u2")
        np.testing.assert_array_equal(got, symbols.ravel(), err_msg=f"case {k}: B = {bits}")
    assert any(b"\xff\xff\xff" in (tmp_path / f"{k}.bin").read_bytes() for k in range(len(cases)))


def test_ac_errors_read_as_in_python(tmp_path):
    """(1.5) A damaged acB array is refused with Python's message, word for word: codec, the first
    byte, a stream cut short or followed by more bytes, garbage, B out of range or spelled otherwise,
    missing or short offset / scale."""
    from stg_runtime import Model, Segment
    seal, split = _from_tools("craft", "seal", "split")
    rng = np.random.default_rng(2)
    n = 50
    segment = Segment(0, 4, opacity=rng.uniform(0, 1, n), t_center=rng.uniform(0, 1, n), t_scale=np.ones(n),
                      position=rng.normal(0, 1, (n, 1, 3)), rotation=np.tile([1.0, 0, 0, 0], (n, 1, 1)),
                      scale=np.full((n, 3), -2.0), features=rng.uniform(0, 1, (n, 3)))
    base = stg_format.dumps(Model("lite", 10.0, [segment]),
                            {"opacity": "ac9", "position": "ac12-delta", "features": "ac4:1+vq/ac6-delta:2"}, codec="raw")

    def opacity(h):
        return h["segments"][0]["attributes"]["opacity"]

    def book(h):
        return h["segments"][0]["attributes"]["features"]["parts"][1]["codebook"]

    def edited(edit=None, poke=None):
        header, section, version = split(base)
        section = bytearray(section)
        if edit:
            edit(header)
        if poke:
            where, values = poke
            at = where(header)["data"]["offset"]
            section[at:at + len(values)] = values
        return seal(header, bytes(section), version)

    def length(where, change):
        return lambda h: where(h)["data"].update(length=where(h)["data"]["length"] + change)

    cases = {
        "zlib": edited(lambda h: opacity(h)["data"].update(codec="zlib")),
        "first_byte": edited(poke=(opacity, b"\x07")),
        "book_first_byte": edited(poke=(book, b"\xff")),
        "cut": edited(length(opacity, -1)), "cut_to_5": edited(lambda h: opacity(h)["data"].update(length=5)),
        "cut_to_4": edited(lambda h: opacity(h)["data"].update(length=4)),
        "empty": edited(lambda h: opacity(h)["data"].update(length=0)),
        "longer": edited(length(opacity, 3)), "book_longer": edited(length(book, 1)),
        "garbage": edited(poke=(opacity, bytes([0]) + rng.integers(0, 256, 40, np.uint8).tobytes())),
        "garbage_ff": edited(poke=(opacity, bytes([0]) + b"\xff" * 30)),
        **{f"encoding_{e}": edited(lambda h, e=e: opacity(h).update(encoding=e))
           for e in ("ac17", "ac07", "ac0", "ac", "ac-delta", "ac9-delta-delta", "ac9delta", "AC9", " ac9", "ac+9")},
        "as_delta": edited(lambda h: opacity(h).update(encoding="ac9-delta")),  # decodes: other values
        "as_fewer_bits": edited(lambda h: opacity(h).update(encoding="ac8")),
        "no_offset": edited(lambda h: opacity(h).pop("offset")),
        "short_scale": edited(lambda h: opacity(h).update(scale=[])),
        "book_no_scale": edited(lambda h: book(h).pop("scale")),
        "book_scale_null": edited(lambda h: book(h).update(scale=None)),
        "huge_scale": edited(lambda h: opacity(h).update(scale=[1e300])),
    }
    for name, data in cases.items():
        (tmp_path / f"{name}.stg").write_bytes(data)
    results = read_many(sorted(tmp_path.glob("*.stg")))
    refused = 0
    for name in cases:
        file = f"{name}.stg"
        python = python_error(tmp_path / file, named=file)
        refused += python is not None
        got = results[file]
        assert got["ok"] == (python is None) and (python is None or got["error"] == python), (got, python)
        if python is None:  # (read as ac9-delta: other values, the same in both)
            assert_reads_as_in_python(tmp_path / file, tmp_path / name)
    assert refused >= len(cases) - 2, refused


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
    mutate_stg = _from_tools("fuzz", "mutate_stg")
    rng = np.random.default_rng(11)
    bases = [p.read_bytes() for p in VECTORS]
    assert bytes([1, 0, 5, 0]) in [b[8:12] for b in bases]  # a 1.5 file (full_ac.stg: acB arrays) among the seeds
    expected = {}
    for k in range(300):
        how, data = mutate_stg(bases[k % len(bases)], rng)
        path = tmp_path / f"f{k:03d}.stg"
        path.write_bytes(data)
        expected[path.name] = python_error(path)
    results = read_many(sorted(tmp_path.glob("*.stg")))
    refused = [n for n, e in expected.items() if e is not None]
    assert len(refused) > 100
    for name in refused:
        assert not results[name]["ok"] and results[name]["type"] == "FormatError", (name, expected[name], results[name])
        assert results[name]["error"].startswith(name + ": ")
        if "arithmetic-coded" in expected[name]:  # (1.5) the range decoder's refusals, word for word
            assert results[name]["error"] == f"{name}: {expected[name].split(': ', 1)[1]}", (expected[name], results[name])
    accepted = [n for n, e in expected.items() if e is None]
    # the one known difference: JSON's NaN / Infinity literals, which Python's json reads and JSON.parse refuses
    differ = [n for n in accepted if not results[n]["ok"] and "JSON" not in results[n]["error"]]
    assert not differ, [results[n] for n in differ]


def test_fuzzed_ac_streams_read_as_in_python(tmp_path):
    """(1.5) full_ac.stg with its acB blobs damaged (1 to 4 bytes replaced, or the blob made 1 to 3 bytes
    shorter or longer): the JS reader accepts what Python accepts, with the same values, and refuses
    the rest with Python's message, word for word."""
    seal, split = _from_tools("craft", "seal", "split")
    header, section, version = split((ROOT / "formats" / "vectors" / "full_ac.stg").read_bytes())
    blobs = []

    def walk(spec):
        if spec.get("encoding", "").startswith("ac"):
            blobs.append(spec["data"])
        for nested in ([spec["codebook"]] if "codebook" in spec else []) + spec.get("parts", []):
            walk(nested)
    for spec in header["segments"][0]["attributes"].values():
        walk(spec)
    assert len(blobs) >= 8
    rng = np.random.default_rng(4)
    expected = {}
    for k in range(200):
        body = bytearray(section)
        blob = blobs[k % len(blobs)]
        original = dict(blob)
        if k % 3:
            for _ in range(rng.integers(1, 5)):
                body[blob["offset"] + rng.integers(blob["length"])] = rng.integers(256)
        else:
            blob["length"] = max(0, blob["length"] + int(rng.choice([-3, -2, -1, 1, 2, 3])))
        data = seal(header, bytes(body), version)
        blob.update(original)
        path = tmp_path / f"a{k:03d}.stg"
        path.write_bytes(data)
        expected[path.name] = python_error(path, named=path.name)
    results = read_many(sorted(tmp_path.glob("*.stg")))
    for name, error in expected.items():
        assert results[name]["ok"] == (error is None) and results[name].get("error") == error, (error, results[name])
    accepted = [n for n, e in expected.items() if e is None]
    assert 20 < len(accepted) < 180, len(accepted)
    assert any("arithmetic-coded" in e for e in expected.values() if e)
    for name in accepted[:5]:  # (a damaged stream may still decode: other values, the same in both)
        assert_reads_as_in_python(tmp_path / name, tmp_path / name.replace(".stg", ""))


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
