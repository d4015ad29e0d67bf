"""PLY reader/writer: round trips in every format, and a PLYError naming the file for every malformed case."""
import numpy as np
import pytest

from stg_train.convert.ply import PLYError, read_ply, require, write_ply


def sample(n=7, seed=0):
    rng = np.random.default_rng(seed)
    return {"x": rng.standard_normal(n).astype(np.float32), "y": rng.standard_normal(n),  # float64 kept
            "red": rng.integers(0, 256, n).astype(np.uint8), "label": rng.integers(-1000, 1000, n).astype(np.int32),
            "s": rng.integers(-100, 100, n).astype(np.int16), "u": rng.integers(0, 2**32 - 1, n).astype(np.uint32)}


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_round_trip_keeps_names_order_types_and_values(tmp_path, fmt):
    props = sample()
    write_ply(tmp_path / "a.ply", props, fmt=fmt, comments=["made by test_ply"])
    got, count = read_ply(tmp_path / "a.ply")
    assert count == 7 and list(got) == list(props)
    for name, want in props.items():
        assert got[name].dtype == want.dtype, name
        np.testing.assert_array_equal(got[name], want, err_msg=name)


def test_writer_defaults_float32_and_keeps_the_file_atomic(tmp_path):
    path = tmp_path / "b.ply"
    write_ply(path, {"a": np.arange(3, dtype=np.float16), "flag": np.array([True, False, True])})
    got, _ = read_ply(path)
    assert got["a"].dtype == np.float32 and got["flag"].dtype == np.uint8
    np.testing.assert_array_equal(got["flag"], [1, 0, 1])
    head = path.read_bytes().split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in head and "property float a" in head
    before = path.read_bytes()
    with pytest.raises(ValueError, match="different lengths"):
        write_ply(path, {"a": np.zeros(3), "b": np.zeros(4)})
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["b.ply"]


def test_reads_vertex_after_other_elements_and_skips_faces(tmp_path):
    head = ("ply\r\nformat binary_little_endian 1.0\r\ncomment x\r\nelement camera 2\r\nproperty float f\r\n"
            "property uchar k\r\nelement vertex 2\r\nproperty float x\r\nproperty double y\r\n"
            "element face 1\r\nproperty list uchar int vertex_indices\r\nend_header\r\n").encode()
    camera = np.zeros(2, np.dtype([("f", "<f4"), ("k", "u1")])).tobytes()
    vertex = np.array([(1.5, 2.5), (-3.0, 4.0)], np.dtype([("x", "<f4"), ("y", "<f8")])).tobytes()
    face = bytes([3]) + np.arange(3, dtype="<i4").tobytes()
    (tmp_path / "c.ply").write_bytes(head + camera + vertex + face)
    got, count = read_ply(tmp_path / "c.ply")
    assert count == 2
    np.testing.assert_array_equal(got["x"], [1.5, -3.0])
    np.testing.assert_array_equal(got["y"], [2.5, 4.0])
    ascii_text = ("ply\nformat ascii 1.0\nelement camera 1\nproperty float f\nelement vertex 2\n"
                  "property float x\nproperty uchar c\nend_header\n9.0\n1.25 7\n-2 255\n")
    (tmp_path / "d.ply").write_text(ascii_text)
    got, _ = read_ply(tmp_path / "d.ply")
    np.testing.assert_array_equal(got["x"], [1.25, -2.0])
    np.testing.assert_array_equal(got["c"], [7, 255])


def good_header(count=2, fmt="binary_little_endian"):
    return (f"ply\nformat {fmt} 1.0\nelement vertex {count}\nproperty float x\nproperty float y\n"
            "end_header\n")


BINARY_ROWS = np.arange(4, dtype="<f4").tobytes()


@pytest.mark.parametrize("content, match", [
    (b"PK\x03\x04 a zip file", "not a PLY file"),
    (b"", "not a PLY file"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n", "no 'end_header'"),
    (b"ply\nformat binary_middle_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n", "unsupported format"),
    (b"ply\nelement vertex 1\nproperty float x\nend_header\n" + bytes(4), "no 'format' line"),
    (b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty float x\nend_header\n" + bytes(4),
     "no 'vertex' element"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty list uchar int idx\nend_header\n",
     "list properties"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float128 x\nend_header\n" + bytes(16),
     "unknown type 'float128'"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex -1\nproperty float x\nend_header\n", "bad element"),
    (b"ply\nformat binary_little_endian 1.0\nproperty float x\nelement vertex 1\nend_header\n", "before any element"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float x\nend_header\n"
     + bytes(8), "duplicate"),
    (good_header(2).encode() + BINARY_ROWS[:12], "truncated: 2 vertices need 16 bytes"),
    (good_header(3).encode() + BINARY_ROWS, "truncated"),
    (good_header(2, "ascii").encode() + b"1 2\n", "truncated: 2 vertices declared, 1"),
    (good_header(2, "ascii").encode() + b"1 2\n3\n", "vertex 1 has 1 values"),
    (good_header(2, "ascii").encode() + b"1 2\n3 abc\n", "property 'y'"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty uchar c\nend_header\n1.5\n", "not a uchar"),
])
def test_malformed_files_raise_plyerror_naming_the_file(tmp_path, content, match):
    path = tmp_path / "broken.ply"
    path.write_bytes(content)
    with pytest.raises(PLYError, match=match) as info:
        read_ply(path)
    assert str(info.value).startswith(str(path))
    assert isinstance(info.value, ValueError)


def test_require_lists_every_missing_property(tmp_path):
    props = {"x": np.zeros(1), "y": np.zeros(1)}
    require(props, ["x", "y"], tmp_path / "p.ply")
    with pytest.raises(PLYError, match=r"p\.ply: missing vertex properties: z, opacity"):
        require(props, ["x", "z", "opacity"], tmp_path / "p.ply")
