"""stg_runtime.format, version 1.4: the `vq` and `parts` encodings (formats/stg-v1.md, "Codebooks and
parts"): round trips, the version written, and every refusal of a crafted file."""
import math
import struct
from dataclasses import replace

import numpy as np
import pytest

from stg_runtime import Limits
from stg_runtime import format as stg
from stg_runtime.model import Model

from .test_format import attr, craft, make_model, refused, split

ENCODINGS = {"features": "vq/u8", "position": "u16-delta:3+vq/f16:9", "rotation": "vq", "scale": "f16:1+vq/u16:2",
             "opacity": "u8-delta"}


def clustered(seed=0, rows=(5, 300), count=40):
    """make_model's full model with features drawn from `rows[0]` distinct rows, motion from
    `rows[1]`, rotation from 7, and scale's last two channels from 4 (the others as they are)."""
    model = make_model(seed, count=count)
    rng = np.random.default_rng(seed)
    segments = []
    for seg in model.segments:
        n = seg.count
        pick = lambda table: table[rng.integers(len(table), size=n)]  # noqa: E731
        position = seg.position.copy()
        position[:, 1:] = pick(rng.normal(0, 1, (rows[1], 3, 3)))
        scale = seg.scale.copy()
        scale[:, 1:] = pick(np.exp(rng.normal(-3, 1, (4, 2))))
        segments.append(replace(seg, features=pick(rng.normal(0, 2, (rows[0], 9))), position=position,
                                rotation=pick(rng.normal(0, 1, (7, 2, 4))), scale=scale))
    return Model(model.kind, model.fps, segments, model.cameras, model.bounds, model.provenance)


@pytest.fixture(scope="module")
def compact_bytes():
    return stg.dumps(clustered(), ENCODINGS)


def test_round_trip_and_version(compact_bytes):
    model = clustered()
    assert struct.unpack_from("<HH", compact_bytes, 8) == (1, 4)
    back = stg.loads(compact_bytes).segments[0]
    seg = model.segments[0]
    for name in ("position", "rotation"):  # motion (f16 codebook of f32 values) and rotation (f32 codebook)
        tol = 2.0 ** -11 * np.abs(seg.position[:, 1:]).max() if name == "position" else 0
        np.testing.assert_allclose(getattr(back, name)[:, 1:], getattr(seg, name)[:, 1:], rtol=0, atol=tol)
    np.testing.assert_array_equal(back.rotation, seg.rotation)
    bound = stg.error_bound(np.unique(seg.features, axis=0), "u8")  # the codebook's u8 bound per channel
    assert np.all(np.abs(back.features - seg.features) <= bound)
    np.testing.assert_allclose(back.position[:, 0], seg.position[:, 0],
                               atol=stg.error_bound(seg.position[:, 0], "u16").max())
    header, _ = split(compact_bytes)
    features = attr(header, "features")
    assert features["encoding"] == "vq" and features["codebook"]["shape"] == [5, 9]
    assert features["data"]["length"] < 40  # 40 one-byte indices, compressed
    assert [p["shape"] for p in attr(header, "position")["parts"]] == [[40, 3], [40, 9]]
    assert {name: stg.encoding_of(attr(header, name)) for name in ENCODINGS} == {**ENCODINGS, "rotation": "vq/f32"}


def test_decoded_values_write_again_to_the_same_values(compact_bytes):
    """What a reader decodes from a vq / parts file, written with the same encodings, decodes to the
    same values up to float32 rounding (codebooks of the distinct rows, quantized again on their own
    grid: as for u8 / u16 arrays, a scale may move by an ulp) in a file of the same size."""
    model = stg.loads(compact_bytes)
    again = stg.dumps(model, ENCODINGS, provenance=model.provenance)
    assert len(again) == len(compact_bytes)
    for a, b in zip(model.segments, stg.loads(again).segments):
        for name, values in a.arrays().items():
            np.testing.assert_allclose(getattr(b, name), values, rtol=0, atol=2.0 ** -21 * np.abs(values).max())


@pytest.mark.parametrize("bits", [8, 16])
def test_delta_encodings_store_channel_major_differences(bits):
    """Differences of each channel in turn; u16-delta's as a plane of low bytes, then of high bytes."""
    model = make_model(count=300)
    plain, delta = f"u{bits}", f"u{bits}-delta"
    header, section = split(stg.dumps(model, {"position": delta}, codec="raw"))
    spec = attr(header, "position")
    dtype = np.dtype("u1" if bits == 8 else "<u2")
    planes = np.frombuffer(section, np.uint8, 300 * 12 * dtype.itemsize, spec["data"]["offset"])
    planes = planes.reshape(dtype.itemsize, 300 * 12).astype(dtype)
    stored = (planes[0] if bits == 8 else planes[0] | planes[1] << 8).reshape(12, 300)
    q, params = stg.quantize(model.segments[0].position, plain)
    assert params == {"offset": spec["offset"], "scale": spec["scale"]}
    np.testing.assert_array_equal(np.cumsum(stored, axis=1, dtype=dtype), q.reshape(300, 12).T)
    assert stored[3, 1] == (int(q[1, 1, 0]) - int(q[0, 1, 0])) % (1 << bits)  # channel 3 = coefficient 1, x
    np.testing.assert_array_equal(stg.loads(stg.dumps(model, {"position": delta})).segments[0].position,
                                  stg.loads(stg.dumps(model, {"position": plain})).segments[0].position)


def test_codebooks_of_more_than_256_rows_take_two_byte_indices():
    model = clustered(rows=(300, 5), count=2000)
    header, _ = split(stg.dumps(model, {"features": "vq/f32"}, codec="raw"))
    assert 256 < attr(header, "features")["codebook"]["shape"][0] <= 300
    assert attr(header, "features")["data"]["length"] == 2 * 2000
    np.testing.assert_array_equal(stg.loads(stg.dumps(model, {"features": "vq"})).segments[0].features,
                                  model.segments[0].features)


def test_empty_segment_and_plain_files():
    model = clustered()
    empty = Model("full", 30.0, [model.segments[0].subset(np.zeros(40, bool))])
    back = stg.loads(stg.dumps(empty, ENCODINGS))
    assert back.segments[0].count == 0 and back.segments[0].position.shape == (0, 4, 3)
    assert struct.unpack_from("<HH", stg.dumps(model, {"features": "u8"}), 8) == (1, 0)


@pytest.mark.parametrize("encodings, match", [
    ({"features": "vq/vq"}, "unknown encoding 'vq/vq'"),
    ({"features": "vq/u8:4+vq/u8:4"}, "covers 8 of 9 channels"),
    ({"position": "u16:3+u16:3:3"}, "bad part"),
    ({"position": "u16:0+vq:12"}, "bad part"),
    ({"position": "+".join(["f32:1"] * 65)}, "more than 64"),
    ({"opacity": "bf16"}, "unknown encoding 'bf16'"),
])
def test_writer_refuses_bad_encodings(encodings, match):
    with pytest.raises(ValueError, match=match):
        stg.dumps(clustered(), encodings)


def test_writer_refuses_more_distinct_rows_than_a_codebook_holds():
    model = make_model(count=65537, segments=1)
    with pytest.raises(ValueError, match="segment 0, attribute 'features': vq: 65537 distinct values"):
        stg.dumps(model, {"features": "vq"})


def _book(h, name="features"):
    return attr(h, name)["codebook"]


@pytest.mark.parametrize("edit, match", [
    (lambda h: _book(h).update(shape=[5, 8]), r"codebook: shape \[5, 8\] disagrees .* expected \[5, 9\]"),
    (lambda h: _book(h).update(shape=[0, 9]), r"codebook's shape must be \[K, 9\] with K in \[1, 65536\]"),
    (lambda h: _book(h).update(shape=[65537, 9]), "K in"),
    (lambda h: _book(h).update(shape="5x9"), "K in"),
    (lambda h: _book(h).update(shape=[4, 9]), "zlib data does not end after 36 bytes"),  # the blob is longer
    (lambda h: attr(h, "features").pop("codebook"), "missing field 'codebook'"),
    (lambda h: _book(h).update(encoding="vq"), "codebook: unknown encoding 'vq' .*not allowed in a codebook"),
    (lambda h: _book(h).update(encoding="parts"), "not allowed in a codebook"),
    (lambda h: _book(h).update(scale=[1e38] * 9), "not all finite"),
    (lambda h: _book(h).update(offset=[0.0] * 8), "lists 'offset' and 'scale' of 9"),
    (lambda h: attr(h, "features")["data"].update(length=3), "zlib|imply"),
    (lambda h: attr(h, "position")["parts"].pop(), "the parts cover 3 channels, the array has 12"),
    (lambda h: attr(h, "position")["parts"][1].update(shape=[40, 10]), "cover 13"),
    (lambda h: attr(h, "position")["parts"][1].update(shape=[40, 0]), r"part 1: shape must be \[40, channels >= 1\]"),
    (lambda h: attr(h, "position")["parts"][1].update(shape=[39, 9]), "part 1: shape .* disagrees"),
    (lambda h: attr(h, "position").update(parts=[]), "0 parts, expected 1 to 64"),
    (lambda h: attr(h, "position").update(parts={}), "'parts' must be of type list"),
    (lambda h: attr(h, "position")["parts"][0].update(encoding="parts"), "part 0: unknown encoding 'parts' .*part"),
    (lambda h: attr(h, "position")["parts"].__setitem__(0, 7), "part 0: shape must be"),
    (lambda h: attr(h, "opacity")["data"].update(length=3), "zlib|imply"),
    (lambda h: attr(h, "opacity").update(scale=[1e38]), "not all finite"),
    (lambda h: attr(h, "opacity").pop("offset"), "u8 needs lists"),
    (lambda h: attr(h, "opacity").update(encoding="u32-delta"), "unknown encoding 'u32-delta'"),
])
def test_crafted_compact_arrays_are_refused(compact_bytes, tmp_path, edit, match):
    refused(craft(compact_bytes, edit, minor=4), match, tmp_path)


def test_an_index_beyond_the_codebook_is_refused(tmp_path):
    model = clustered()
    data = stg.dumps(model, {"features": "vq/f32"}, codec="raw")
    header, section = split(data)
    spec = attr(header, "features")
    at = spec["data"]["offset"]
    index = np.frombuffer(section[at:at + 40], np.uint8).copy()
    index[17] = 5  # the codebook has rows 0..4
    section = section[:at] + index.tobytes() + section[at + 40:]
    from .test_format import seal
    refused(seal(header, section, minor=4), r"segment 0, attribute 'features': index 5 beyond the codebook's 5 rows",
            tmp_path)


def test_codebooks_count_in_the_memory_limit():
    data = stg.dumps(clustered(), ENCODINGS)
    needed = stg.loads(data)  # loads with the defaults
    arrays = sum(v.size for s in needed.segments for v in s.arrays().values())
    header, _ = split(data)
    books = sum(math.prod(e["codebook"]["shape"]) for name in ENCODINGS
                for e in [attr(header, name)] + attr(header, name).get("parts", []) if e["encoding"] == "vq")
    assert books > 100
    limits = Limits(max_expansion=0, expansion_allowance=4 * (arrays + books))
    stg.loads(data, limits=limits)
    with pytest.raises(stg.FormatError, match="would take"):
        stg.loads(data, limits=replace(limits, expansion_allowance=4 * (arrays + books) - 1))
