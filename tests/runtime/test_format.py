"""stg_runtime.format: the .stg reader and writer (formats/stg-v1.md, section 4)."""
import hashlib
import json
import os
import struct
import subprocess
import sys
import zlib

import numpy as np
import pytest

from stg_runtime import Camera, Model, Segment
from stg_runtime import format as stg
from stg_runtime.model import ATTRIBUTES
from stg_runtime.onnx_mlp import mlp_to_onnx

ENCODINGS = ("f32", "f16", "u8", "u16")


# -- builders -----------------------------------------------------------------------------------


def make_segment(rng, kind="full", start=0, frames=50, count=40, pdeg=3, qdeg=1, activation="sigmoid"):
    channels = 9 if kind == "full" else 3
    decoder = None
    if kind == "full":
        decoder = mlp_to_onnx([rng.standard_normal((6, 12)).astype(np.float32),
                               rng.standard_normal((3, 6)).astype(np.float32)])
    return Segment(start, frames, opacity=rng.uniform(0, 1, count), t_center=rng.uniform(0, 1, count),
                   t_scale=rng.uniform(0, 50, count), position=rng.normal(0, 3, (count, pdeg + 1, 3)),
                   rotation=rng.normal(0, 1, (count, qdeg + 1, 4)), scale=np.exp(rng.normal(-3, 1, (count, 3))),
                   features=rng.normal(0, 2, (count, channels)), decoder=decoder, activation=activation)


def make_model(seed=0, kind="full", segments=1, **kw):
    rng = np.random.default_rng(seed)
    segs = [make_segment(rng, kind, start=50 * i, activation=("sigmoid", "clamp", "identity")[i % 3], **kw)
            for i in range(segments)]
    cams = [Camera.look_at((i, 0.5, -4), (0, 0, 0), (0, -1, 0), 50, 64, 48, name=f"cam{i:02d}") for i in range(3)]
    return Model(kind, 30.0, segs, cameras=cams, bounds=((-1.5, -2.0, 0.5), (1.5, 2.0, 8.25)),
                 provenance={"tool": "test", "settings": {"seed": seed, "lr": [1e-3, 2e-4]}})


def assert_models_equal(a, b, exact=True):
    for key in ("kind", "fps", "num_frames", "bounds", "provenance"):
        assert getattr(a, key) == getattr(b, key), key
    assert [c.to_dict() for c in a.cameras] == [c.to_dict() for c in b.cameras]
    assert len(a.segments) == len(b.segments)
    for sa, sb in zip(a.segments, b.segments):
        assert (sa.start_frame, sa.num_frames, sa.decoder, sa.activation) == \
               (sb.start_frame, sb.num_frames, sb.decoder, sb.activation)
        for name in ATTRIBUTES:
            x, y = getattr(sa, name), getattr(sb, name)
            assert x.dtype == y.dtype == np.float32 and x.shape == y.shape
            if exact:
                np.testing.assert_array_equal(x, y)


# -- crafting files: edit the header, keep the checksum valid ---------------------------------------


def split(data):
    magic, major, minor, length = struct.unpack_from("<8sHHQ", data)
    return json.loads(data[20:20 + length]), data[20 + length:-32]


def seal(header, section, major=1, minor=0, magic=stg.MAGIC):
    text = json.dumps(header).encode() if isinstance(header, dict) else header
    body = struct.pack("<8sHHQ", magic, major, minor, len(text)) + text + section
    return body + hashlib.sha256(body).digest()


def craft(data, edit=None, extra=b"", **kw):
    """The file `data` with edit(header) applied, `extra` bytes appended to the data section, resealed."""
    header, section = split(data)
    if edit:
        edit(header)
    return seal(header, section + extra, **kw)


@pytest.fixture(scope="module")
def full_bytes():
    return stg.dumps(make_model(segments=2), codec="raw")


def attr(header, name, segment=0):
    return header["segments"][segment]["attributes"][name]


def refused(data, match, tmp_path):
    """Load `data` from a file; it must raise FormatError naming the file and matching `match`."""
    path = tmp_path / "crafted.stg"
    path.write_bytes(data)
    with pytest.raises(stg.FormatError, match=match) as info:
        stg.load(path)
    assert str(info.value).startswith(str(path) + ": ")
    return info.value


# -- round trips --------------------------------------------------------------------------------


@pytest.mark.parametrize("codec", ["raw", "zlib"])
def test_round_trip_three_segments_exact(tmp_path, codec):
    model = make_model(segments=3)
    path = tmp_path / "scene.stg"
    stg.save(model, path, codec=codec)
    loaded = stg.load(path)
    assert_models_equal(model, loaded)
    assert [s.activation for s in loaded.segments] == ["sigmoid", "clamp", "identity"]
    assert loaded.num_frames == 150 and loaded.segments[2].start_frame == 100
    assert os.listdir(tmp_path) == ["scene.stg"]
    assert stg.loads(path.read_bytes()).provenance == model.provenance


def test_round_trip_lite_and_empty_segment():
    rng = np.random.default_rng(1)
    model = Model("lite", 24, [make_segment(rng, "lite", count=0, pdeg=1, qdeg=0),
                               make_segment(rng, "lite", start=50, frames=10, count=7)])
    for enc in ENCODINGS:
        loaded = stg.loads(stg.dumps(model, encodings={n: enc for n in ATTRIBUTES}))
        assert_models_equal(model, loaded, exact=enc == "f32")
    loaded = stg.loads(stg.dumps(model, provenance={"tool": "other"}))
    assert loaded.provenance == {"tool": "other"} and loaded.bounds is None and loaded.cameras == []
    assert loaded.segments[0].decoder is None and loaded.segments[0].position.shape == (0, 2, 3)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_quantized_round_trip_within_bound(encoding):
    model = make_model(seed=2, count=300)
    loaded = stg.loads(stg.dumps(model, encodings={n: encoding for n in ATTRIBUTES}))
    assert_models_equal(model, loaded, exact=encoding == "f32")
    for name in ATTRIBUTES:
        x, y = getattr(model.segments[0], name), getattr(loaded.segments[0], name)
        err = np.abs(y.astype(np.float64) - x).reshape(len(x), -1)
        assert np.all(err <= stg.error_bound(x, encoding)), name


def test_error_bounds_match_the_spec_table():
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.normal(0, 100, (500, 3)), rng.normal(0, 1e-6, (500, 3))]).astype(np.float32)
    assert stg.error_bound(x, "f32") == 0.0
    f16 = stg.error_bound(x, "f16")
    a = np.abs(x.astype(np.float64))
    np.testing.assert_array_equal(f16, np.where(a >= 2.0**-14, 2.0**-11 * a, 2.0**-25))
    err = np.abs(stg.dequantize(stg.quantize(x, "f16")[0], "f16") - x.astype(np.float64))
    assert np.all(err <= f16) and np.any(err > 0.5 * f16)
    for encoding, bits in (("u8", 8), ("u16", 16)):
        stored, params = stg.quantize(x, encoding)
        assert stored.dtype == np.dtype(f"<u{bits // 8}") and stored.shape == x.shape
        lo, hi = x.min(0).astype(np.float64), x.max(0).astype(np.float64)
        np.testing.assert_array_equal(params["offset"], lo)
        scale = np.array(params["scale"])
        assert np.all(scale >= (hi - lo) / (2**bits - 1)) and np.allclose(scale, (hi - lo) / (2**bits - 1), rtol=1e-7)
        bound = stg.error_bound(x, encoding)
        np.testing.assert_allclose(bound, scale / 2 + 2.0**-23 * np.maximum(np.abs(lo), np.abs(hi)), rtol=1e-12)
        err = np.abs(stg.dequantize(stored, encoding, params) - x.astype(np.float64))
        assert np.all(err <= bound) and np.all(err.max(0) > 0.4 * scale)  # tight: near scale / 2


def test_quantize_edge_cases():
    const = np.full((10, 2, 3), 7.25, np.float32)
    for encoding in ENCODINGS:
        stored, params = stg.quantize(const, encoding)
        np.testing.assert_array_equal(stg.dequantize(stored, encoding, params), const)
    assert stg.quantize(const, "u8")[1]["scale"] == [0.0] * 6
    with pytest.raises(ValueError, match="65504"):
        stg.quantize(np.array([70000.0], np.float32), "f16")
    with pytest.raises(ValueError, match="non-finite"):
        stg.quantize(np.array([1.0, np.inf], np.float32), "u8")
    with pytest.raises(ValueError, match="unknown encoding"):
        stg.quantize(const, "f8")


def test_save_refuses_bad_values_and_leaves_nothing(tmp_path):
    model = make_model()
    model.segments[0].position[3, 1, 2] = np.nan
    with pytest.raises(ValueError, match="position"):
        stg.save(model, tmp_path / "bad.stg")
    model = make_model()
    model.segments[0].scale[0, 0] = 1e5
    with pytest.raises(ValueError, match="segment 0, attribute 'scale'.*65504"):
        stg.save(model, tmp_path / "bad.stg", encodings={"scale": "f16"})
    for encodings in ({"scale": "f8"}, {"colour": "f16"}):
        with pytest.raises(ValueError, match="f8|colour"):
            stg.save(make_model(), tmp_path / "bad.stg", encodings=encodings)
    with pytest.raises(ValueError, match="codec"):
        stg.save(make_model(), tmp_path / "bad.stg", codec="lz4")
    assert os.listdir(tmp_path) == []


def test_save_replaces_atomically_and_cleans_up_on_write_error(tmp_path, monkeypatch):
    path = tmp_path / "scene.stg"
    stg.save(make_model(seed=1), path)
    before = path.read_bytes()

    def fail(fd):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(OSError, match="disk full"):
        stg.save(make_model(seed=2), path)
    assert os.listdir(tmp_path) == ["scene.stg"] and path.read_bytes() == before


def test_file_written_by_another_process(tmp_path):
    path = tmp_path / "other.stg"
    code = ("import tests.runtime.test_format as t; "
            f"t.stg.save(t.make_model(seed=5, segments=2), {str(path)!r}, encodings={{'features': 'u8'}})")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
    here = stg.loads(stg.dumps(make_model(seed=5, segments=2), encodings={"features": "u8"}))
    assert_models_equal(here, stg.load(path))


def test_layout(full_bytes):
    assert full_bytes[:8] == b"\x89STG\r\n\x1a\n" and struct.unpack_from("<HH", full_bytes, 8) == (1, 0)
    header, section = split(full_bytes)
    assert (20 + struct.unpack_from("<Q", full_bytes, 12)[0]) % 8 == 0
    assert full_bytes[-32:] == hashlib.sha256(full_bytes[:-32]).digest()
    blobs = [a["data"] for s in header["segments"] for a in s["attributes"].values()]
    blobs += [s["decoder"]["data"] for s in header["segments"]]
    assert all(b["offset"] % 8 == 0 and b["offset"] + b["length"] <= len(section) for b in blobs)
    assert header["num_frames"] == 100 and header["kind"] == "full" and len(header["cameras"]) == 3


# -- what a reader refuses ------------------------------------------------------------------------


def test_truncated_files_are_refused(full_bytes, tmp_path):
    length = struct.unpack_from("<Q", full_bytes, 12)[0]
    for cut in (0, 5, 19, 20, 20 + length // 2, 20 + length + 1, len(full_bytes) // 2, len(full_bytes) - 1):
        refused(full_bytes[:cut], "truncated", tmp_path)


def test_any_flipped_byte_is_refused(full_bytes, tmp_path):
    for pos in np.linspace(0, len(full_bytes) - 1, 40).astype(int):
        bad = bytearray(full_bytes)
        bad[pos] ^= 0x10
        with pytest.raises(stg.FormatError):
            stg.loads(bytes(bad), "x.stg")
    refused(full_bytes[:-40] + bytes([full_bytes[-40] ^ 1]) + full_bytes[-39:], "checksum", tmp_path)


def test_wrong_magic_and_major_version(full_bytes, tmp_path):
    refused(craft(full_bytes, magic=b"\x89PNG\r\n\x1a\n"), "magic", tmp_path)
    refused(craft(full_bytes, major=2), r"version 2\.0", tmp_path)
    refused(struct.pack("<8sHHQ", stg.MAGIC, 1, 0, 1 << 40) + bytes(64), "header length", tmp_path)


def test_newer_minor_version_with_additions_loads(full_bytes):
    end = len(split(full_bytes)[1])

    def add(h):  # an unknown key, an unknown attribute in an unknown encoding, an unreferenced blob
        h["future_key"] = {"anything": [1, 2]}
        h["segments"][0]["attributes"]["normals"] = {"shape": [40, 3], "encoding": "f9",
                                                     "data": {"offset": end, "length": 8, "codec": "zlib"}}
        h["segments"][1]["extra"] = {"note": "blob at end + 8 is referenced by nothing we know"}

    data = craft(full_bytes, add, extra=bytes(16), minor=7)
    assert struct.unpack_from("<HH", data, 8) == (1, 7)
    assert_models_equal(stg.loads(full_bytes), stg.loads(data))


@pytest.mark.parametrize("edit, match", [
    (lambda h: attr(h, "opacity")["data"].update(offset=10**9), "outside"),
    (lambda h: attr(h, "opacity")["data"].update(offset=-8), "outside"),
    (lambda h: attr(h, "scale")["data"].update(length=10**9), "outside"),
    (lambda h: attr(h, "scale")["data"].update(length=8), "imply"),
    (lambda h: attr(h, "position").update(shape=[40, 3, 3]), "shape"),
    (lambda h: h["segments"][0].update(count=41), "shape"),
    (lambda h: h["segments"][0]["attributes"].pop("rotation"), "missing attribute 'rotation'"),
    (lambda h: h["segments"][1].update(start_frame=60), "segment 1 starts at frame 60"),
    (lambda h: h["segments"].reverse(), "segment 1 starts at frame 0"),
    (lambda h: h.update(num_frames=99), "num_frames"),
    (lambda h: h.pop("fps"), "missing field 'fps'"),
    (lambda h: h.update(fps="30"), "'fps' must be"),
    (lambda h: h.update(kind="ultra"), "kind"),
    (lambda h: h.update(segments=[]), "no segments"),
    (lambda h: h["segments"][0].update(count=True), "'count' must be"),
    (lambda h: h["segments"][0].update(decoder=None), "needs decoder"),
    (lambda h: h["segments"][0]["decoder"].update(activation="tanh"), "activation"),
    (lambda h: h["segments"][0]["decoder"]["data"].update(codec="zlib"), "codec"),
    (lambda h: h["segments"][0]["decoder"]["data"].update(length=7), "decoder"),
    (lambda h: attr(h, "features").update(encoding="u8"), "imply"),
    (lambda h: attr(h, "features").update(encoding="bf16"), "unknown encoding"),
    (lambda h: h["cameras"][0].pop("fx"), "camera 0"),
    (lambda h: h.update(bounds={"min": [0, 0], "max": [1, 1, 1]}), "bounds"),
])
def test_semantically_bad_files_are_refused(full_bytes, tmp_path, edit, match):
    refused(craft(full_bytes, edit), match, tmp_path)


def test_header_not_an_object_or_not_json(full_bytes, tmp_path):
    _, section = split(full_bytes)
    refused(seal(b"[1, 2]", section), "not a JSON object", tmp_path)
    refused(seal(b"{not json", section), "Expecting", tmp_path)
    refused(seal(b"\xff\xfe{}", section), "utf-8", tmp_path)
    refused(seal(b"[" * 100000, section), "malformed|JSON", tmp_path)


def test_non_finite_values_are_refused(full_bytes, tmp_path):
    header, section = split(full_bytes)
    section = bytearray(section)
    blob = attr(header, "t_scale")["data"]
    section[blob["offset"] + 4:blob["offset"] + 8] = struct.pack("<f", np.nan)
    refused(seal(header, bytes(section)), "t_scale.*not all finite", tmp_path)
    refused(craft(full_bytes, lambda h: attr(h, "opacity").update(
        encoding="u16", shape=[40], offset=[0.0], scale=[1e38], data={"offset": 0, "length": 80, "codec": "raw"})),
        "not all finite", tmp_path)
    refused(craft(full_bytes, lambda h: attr(h, "opacity").update(
        encoding="u8", offset=[0.0, 1.0], scale=[1.0], data={"offset": 0, "length": 40, "codec": "raw"})),
        "offset", tmp_path)


def test_zlib_bomb_is_refused_without_inflating(full_bytes, tmp_path):
    import tracemalloc
    bomb = zlib.compress(bytes(200 << 20), 9)  # 200 MiB of zeros in ~200 KiB
    offset = len(split(full_bytes)[1])

    def point(h):
        attr(h, "opacity")["data"] = {"offset": offset, "length": len(bomb), "codec": "zlib"}

    data = craft(full_bytes, point, extra=bomb)
    tracemalloc.start()
    refused(data, "zlib data does not end after 160 bytes", tmp_path)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 2 * len(data) + (1 << 20)
    for stream, match in ((zlib.compress(bytes(100)), "holds 100 bytes.*imply 160"),
                          (zlib.compress(bytes(160))[:-3], "does not end"),
                          (zlib.compress(bytes(160)) + b"junk", "does not end")):
        refused(craft(full_bytes, lambda h: attr(h, "opacity").update(
            data={"offset": offset, "length": len(stream), "codec": "zlib"}), extra=stream), match, tmp_path)


def test_decoder_with_external_data_is_refused(full_bytes, tmp_path):
    import onnx
    from onnx import external_data_helper
    header, section = split(full_bytes)
    blob = header["segments"][0]["decoder"]["data"]
    model = onnx.load_from_string(bytes(section[blob["offset"]:blob["offset"] + blob["length"]]))
    external_data_helper.convert_model_to_external_data(model, location="weights.bin", size_threshold=0)
    decoder = model.SerializeToString()
    header["segments"][0]["decoder"]["data"] = {"offset": len(section), "length": len(decoder), "codec": "raw"}
    refused(seal(header, section + decoder), "segment 0, decoder: .*external data", tmp_path)
    garbage = b"\x0b not onnx"
    header["segments"][0]["decoder"]["data"] = {"offset": len(section), "length": len(garbage), "codec": "raw"}
    refused(seal(header, section + garbage), "segment 0, decoder", tmp_path)


# -- camera models (1.2) ----------------------------------------------------------------------------

VECTORS = os.path.join(os.path.dirname(__file__), "..", "..", "formats", "vectors")


def fisheye_model():
    model = make_model()
    fish = Camera(20.0, 21.0, 31.5, 24.5, 64, 48, model.cameras[1].world_to_camera, "fish", "fisheye",
                  (0.05, -0.01, 0.002, -5e-4))
    return Model(model.kind, model.fps, model.segments, [model.cameras[0], fish], model.bounds, model.provenance)


@pytest.mark.parametrize("name", ["full", "lite", "sh"])
def test_pinhole_files_keep_their_bytes(name):
    """Writing a vector file's model again gives the file's bytes: version 1.0 (1.1 for sh), no camera
    model in its camera objects."""
    with open(os.path.join(VECTORS, f"{name}.stg"), "rb") as f:
        data = f.read()
    model = stg.loads(data)
    assert stg.dumps(model, provenance=model.provenance) == data
    header, _ = split(data)
    assert all("model" not in c for c in header["cameras"])


def test_fisheye_cameras_round_trip_in_a_1_2_file():
    model = fisheye_model()
    data = stg.dumps(model)
    assert struct.unpack_from("<HH", data, 8) == (1, 2)
    header, _ = split(data)
    assert header["cameras"][1]["model"] == "fisheye" and "fx" not in header["cameras"][1]
    assert header["cameras"][1]["intrinsics"]["k4"] == -5e-4
    again = stg.loads(data)
    assert again.cameras == model.cameras and again.cameras[1].distortion == (0.05, -0.01, 0.002, -5e-4)
    assert_models_equal(model, again)
    # the same model with pinhole cameras only is a 1.0 file
    plain = Model(model.kind, model.fps, model.segments, model.cameras[:1], model.bounds, model.provenance)
    assert struct.unpack_from("<HH", stg.dumps(plain), 8) == (1, 0)


def old_reader_camera(d):
    """How 1.0 and 1.1 readers of this project built a camera from its object (Camera.from_dict then):
    the pinhole intrinsics at the top level, other keys ignored."""
    return (d["fx"], d["fy"], d["cx"], d["cy"], d["width"], d["height"], d["world_to_camera"], d.get("name", ""))


def test_fisheye_cameras_are_refused_by_every_reader_that_cannot_show_them(tmp_path):
    data = stg.dumps(fisheye_model())
    header, _ = split(data)
    old_reader_camera(header["cameras"][0])  # a pinhole reads as before ...
    with pytest.raises(KeyError, match="fx"):  # ... a fisheye is refused (FormatError "camera 1: invalid")
        old_reader_camera(header["cameras"][1])
    refused(craft(data, lambda h: h["cameras"][1].update(model="omnidirectional")),
            "camera 1: invalid .*unknown camera model 'omnidirectional'", tmp_path)
    refused(craft(data, lambda h: h["cameras"][1]["intrinsics"].pop("k2")), "camera 1: invalid .*k2", tmp_path)
    refused(craft(data, lambda h: h["cameras"][1]["intrinsics"].update(k3="x")), "camera 1: invalid", tmp_path)
    refused(craft(data, lambda h: h["cameras"][1]["intrinsics"].update(fx=0)), "camera 1: invalid .*focal", tmp_path)
