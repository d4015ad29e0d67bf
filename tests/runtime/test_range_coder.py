"""Format 1.5's range coder (stg_runtime.range_coder) against the spec's decoding steps written out in
plain Python, its compression against the entropy, its refusals, and acB arrays through format.py."""
import numpy as np
import pytest

from stg_runtime import format as stg_format
from stg_runtime import range_coder
from stg_runtime.demo import demo_model


def spec_decode(data: bytes, channels: int, count: int, bits: int) -> np.ndarray:
    """formats/stg-v1.md, "Arithmetic-coded fixed point (1.5)", step by step in Python integers."""
    assert data[0] == 0
    rng, code, at = 2**32 - 1, int.from_bytes(data[1:5], "big"), 5
    out = np.zeros((channels, count), np.int64)
    for c in range(channels):
        p = [1024] * (1 << bits)
        for i in range(count):
            node = 1
            for _ in range(bits):
                bound = (rng >> 11) * p[node]
                if code < bound:
                    rng, p[node], bit = bound, p[node] + ((2048 - p[node]) >> 5), 0
                else:
                    code, rng, p[node], bit = code - bound, rng - bound, p[node] - (p[node] >> 5), 1
                node = 2 * node + bit
                while rng < 2**24:
                    rng, code, at = rng << 8, ((code << 8) | data[at]) % 2**32, at + 1
            out[c, i] = node - (1 << bits)
    assert at == len(data), "the stream holds exactly the bytes the steps read"
    return out


def sources(bits: int, rng) -> list[np.ndarray]:
    top = 1 << bits
    return [rng.integers(0, top, (3, 200)),                                    # uniform
            np.clip(rng.normal(top / 2, top / 20 + 0.5, (2, 300)), 0, top - 1).astype(np.int64),  # peaked
            np.full((1, 150), top - 1), np.zeros((2, 0), np.int64),             # constant, empty
            np.tile([0, top - 1], (1, 100))]                                    # alternating extremes


@pytest.mark.parametrize("bits", [1, 2, 5, 8, 12, 16])
def test_streams_decode_as_the_spec_says(bits):
    rng = np.random.default_rng(bits)
    for symbols in sources(bits, rng):
        data = range_coder.encode(symbols, bits)
        np.testing.assert_array_equal(range_coder.decode(data, *symbols.shape, bits), symbols)
        if symbols.size <= 600:
            np.testing.assert_array_equal(spec_decode(data, *symbols.shape, bits), symbols)


def test_a_skewed_source_is_coded_near_its_entropy():
    rng = np.random.default_rng(0)
    probs = np.array([0.7, 0.15, 0.1, 0.05])
    symbols = rng.choice(4, size=(1, 50000), p=probs)
    entropy_bytes = -(probs * np.log2(probs)).sum() * symbols.size / 8
    size = len(range_coder.encode(symbols, 2))
    assert entropy_bytes < size < 1.03 * entropy_bytes + 16


def test_streams_that_are_not_whole_are_refused():
    symbols = np.random.default_rng(1).integers(0, 64, (2, 500))
    data = range_coder.encode(symbols, 6)
    for bad, match in ((data[:-1], "ends before its 1000 values"), (data + b"\0", "has 1 bytes after"),
                       (b"\1" + data[1:], "must start with a 0 byte"), (b"", "must start with a 0 byte"),
                       (b"\0\0\0", "ends before")):
        with pytest.raises(ValueError, match=match):
            range_coder.decode(bad, 2, 500, 6)
    with pytest.raises(ValueError, match="bits must be 1 to 16"):
        range_coder.encode(symbols, 17)
    with pytest.raises(ValueError, match=r"symbols must lie in \[0, 32\)"):
        range_coder.encode(symbols, 5)


def test_ac_channels_that_span_zero_have_zero_on_a_level():
    """The acB writer's rule: exact zeros decode to 0 (float32 rounding), within the bound, and values
    already on the levels are written again to the same values; channels that do not span 0, and u8 /
    u16, keep offset = min."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(500, 3)).astype(np.float32)
    x[:200, :2] = 0.0
    x[:, 2] = np.abs(x[:, 2]) + 0.5
    for bits in (2, 5, 12, 16):
        stored, params = stg_format.quantize(x, f"ac{bits}")
        back = stg_format.dequantize(stored, f"ac{bits}", params)
        assert np.all(np.abs(back[:200, :2]) <= 1e-6 * np.abs(x).max())
        assert np.all(np.abs(back - x) <= stg_format.error_bound(x, f"ac{bits}"))
        stored2, params2 = stg_format.quantize(back, f"ac{bits}")
        np.testing.assert_allclose(stg_format.dequantize(stored2, f"ac{bits}", params2), back, rtol=0, atol=1e-6)
        assert params["offset"][2] == x[:, 2].min()
    assert stg_format.quantize(x, "u8")[1]["offset"] == list(x.min(axis=0).astype(np.float64))


def test_the_format_allows_the_widths_the_coder_codes():
    assert stg_format.MAX_AC_BITS == range_coder.MAX_BITS


def test_ac_arrays_round_trip_within_the_fixed_point_bound():
    """Every B, plain and as differences, in parts beside 1.0 encodings and as a codebook: decoded
    values within the u8 / u16 bound at 2^B - 1 levels; the file says 1.5 (1.4 without acB)."""
    model = demo_model()
    seg = model.segments[0]
    for bits in (1, 3, 7, 10, 16):
        encodings = {"opacity": f"ac{bits}", "t_center": f"ac{bits}-delta", "scale": f"ac{bits}:1+f16:2",
                     "features": f"vq/ac{bits}"}
        data = stg_format.dumps(model, encodings=encodings)
        assert stg_format.PREFIX.unpack_from(data)[1:3] == (1, 5)
        back = stg_format.loads(data).segments[0]
        for name in ("opacity", "t_center"):
            bound = stg_format.error_bound(getattr(seg, name), f"ac{bits}")
            assert np.all(np.abs(getattr(back, name) - getattr(seg, name)).reshape(seg.count, -1) <= bound)
        scale_bound = stg_format.error_bound(seg.scale[:, :1], f"ac{bits}")
        assert np.all(np.abs(back.scale[:, :1] - seg.scale[:, :1]) <= scale_bound)
    assert stg_format.PREFIX.unpack_from(stg_format.dumps(model, encodings={"opacity": "u8-delta"}))[1:3] == (1, 4)
    for bad in ("ac0", "ac17", "ac07", "ac", "ac٣"):
        with pytest.raises(ValueError, match="unknown encoding"):
            stg_format.dumps(model, encodings={"opacity": bad})
