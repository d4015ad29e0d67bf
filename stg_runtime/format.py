"""Read and write `.stg` files, exactly as formats/stg-v1.md section 4 says.

A file is: magic, version, header length, a UTF-8 JSON header, a data section of blobs, and the SHA-256
of everything before it. Nothing is unpickled or executed. Every problem with a file raises FormatError,
whose message starts with the file's name.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from . import onnx_mlp
from .atomic import write_atomic
from .camera import Camera
from .model import ACTIVATIONS, ATTRIBUTES, FEATURE_CHANNELS, KINDS, Model, Segment, allowed_channels, attribute_shape

MAGIC = b"\x89STG\r\n\x1a\n"
VERSION = (1, 5)  # the version this module reads and writes; see written_version()
MAX_SPAN = 2 ** 24  # the largest context_frames / crossfade_frames value a reader accepts (1.3)
PREFIX = struct.Struct("<8sHHQ")  # magic, major, minor, header length
MAX_HEADER = 64 << 20
ALIGN = 8
ENCODINGS = {"f32": np.dtype("<f4"), "f16": np.dtype("<f2"), "u8": np.dtype("u1"), "u16": np.dtype("<u2")}
DELTA = {"u8-delta": "u8", "u16-delta": "u16"}  # (1.4) u8 / u16 as channel-major differences, byte planes
PLAIN = (*ENCODINGS, *DELTA)  # encodings of one number per value (and (1.5) the acB ones, see ac_bits)
CODECS = ("raw", "zlib")
MAX_CODEBOOK = 1 << 16  # rows of a "vq" codebook (1.4)
MAX_PARTS = 64  # parts of a "parts" array (1.4)
MAX_AC_BITS = 16  # (1.5) the largest B of "acB" (range_coder.MAX_BITS; the coder, numba, is imported when used)


class FormatError(ValueError):
    """A file that is not a valid .stg file; the message starts with the file's name."""


@dataclass(frozen=True)
class Limits:
    """What a file may declare, checked before anything large is allocated (formats/stg-v1.md, "Limits").

    The defaults hold the models this project makes with room to spare; to open an honest bigger model,
    pass larger ones: load(path, limits=Limits(max_gaussians=...)), or Player(path, limits=...).
    max_gaussians: per segment; max_segments; max_frames: of the whole video; max_degree: of the
    position and rotation polynomials; decoded arrays (and format 1.4's codebooks) may take at most
    max_expansion x the file's size plus expansion_allowance bytes (a zlib bomb cannot make a small
    file large in memory);
    max_image_side: a stored camera's width and height, in pixels.
    """

    max_gaussians: int = 1 << 24
    max_segments: int = 4096
    max_frames: int = 1 << 24
    max_degree: int = 8
    max_expansion: float = 64.0
    expansion_allowance: int = 64 << 20
    max_image_side: int = 16384


DEFAULT_LIMITS = Limits()


# -- quantization (spec table "Quantization and its error bounds") --------------------------------


def ac_bits(encoding: str) -> int | None:
    """B of a (1.5) arithmetic-coded encoding "acB" or "acB-delta" (B in 1..16, ASCII digits, no
    leading zero), None for any other."""
    name = encoding[:-len("-delta")] if encoding.endswith("-delta") else encoding
    digits = name[2:]
    if name[:2] != "ac" or not (digits.isascii() and digits.isdigit()) or digits[0] == "0":
        return None
    if not 1 <= int(digits) <= MAX_AC_BITS:
        return None
    return int(digits)


def _plain(encoding: str) -> bool:
    return encoding in PLAIN or ac_bits(encoding) is not None


def _levels(encoding: str) -> int:
    """The top integer of a fixed-point encoding: 2^bits - 1."""
    bits = ac_bits(encoding)
    return (1 << bits) - 1 if bits is not None else int(np.iinfo(ENCODINGS[encoding]).max)


def _channels(a: np.ndarray) -> np.ndarray:
    """(N, ...) -> (N, channels): every axis but the first flattened."""
    if a.ndim == 0:
        raise ValueError("an array needs a first (count) axis")
    return a.reshape(a.shape[0], math.prod(a.shape[1:]))


def _round_up(exact: np.ndarray) -> np.ndarray:
    """float64 -> the float32 values at or just above."""
    scale = exact.astype(np.float32)
    return np.where(scale < exact, np.nextafter(scale, np.float32(np.inf)), scale)


def _affine(a: np.ndarray, encoding: str) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel float32 (offset, scale) of a fixed-point `encoding` with `levels` = _levels(encoding):
    (min, (max - min) / levels), scale rounded up to float32.

    acB (the writer's rule, formats/stg-v1.md "Arithmetic-coded fixed point"): a channel whose
    values span 0 (min <= 0 <= max, min < max; levels >= 2) gets scale = (max - min) /
    (levels - 1), rounded up, and offset = scale x floor(min / scale), so that 0 is a level and the
    levels still cover [min, max]; values on those levels give the same levels again."""
    x = _channels(a)
    if x.shape[0] == 0:
        return np.zeros(x.shape[1], np.float32), np.zeros(x.shape[1], np.float32)
    levels = _levels(encoding)
    lo, hi = x.min(axis=0), x.max(axis=0)
    span = hi.astype(np.float64) - lo
    offset, scale = lo, _round_up(span / levels)
    if ac_bits(encoding) is not None and levels >= 2:
        spans_zero = (lo <= 0) & (hi >= 0) & (span > 0)
        step = _round_up(span / (levels - 1)).astype(np.float64)
        below = np.floor(lo / np.where(spans_zero, step, 1.0)) * step
        offset = np.where(spans_zero, below, lo).astype(np.float32)
        scale = np.where(spans_zero, step, scale).astype(np.float32)
    return offset, scale


def quantize(array, encoding: str) -> tuple[np.ndarray, dict]:
    """array (N, ...) -> (stored values of the same shape in the encoding's little-endian dtype, params).

    params is {} for f32 / f16 and {"offset": [C floats], "scale": [C floats]} for u8 / u16, with C the
    channel count (every axis but the first flattened). Raises ValueError for non-finite values, values
    beyond +-65504 under f16, and unknown encodings.
    """
    if encoding not in ENCODINGS and ac_bits(encoding) is None:
        raise ValueError(f"unknown encoding {encoding!r} (expected one of {sorted(ENCODINGS)} or acB, B = 1..16)")
    a = np.asarray(array, dtype=np.float32)
    if not np.all(np.isfinite(a)):
        raise ValueError("non-finite values cannot be written")
    if encoding == "f16" and a.size and np.abs(a).max() > 65504:
        raise ValueError(f"values up to {np.abs(a).max():g} do not fit f16 (|x| <= 65504)")
    if encoding in ("f32", "f16"):
        return a.astype(ENCODINGS[encoding]), {}
    levels = _levels(encoding)
    offset, scale = _affine(a, encoding)
    q = np.rint((_channels(a) - offset.astype(np.float64)) / np.where(scale > 0, scale, 1.0))
    stored = np.clip(q, 0, levels).astype(ENCODINGS.get(encoding, np.dtype("<u2"))).reshape(a.shape)
    return stored, {"offset": offset.tolist(), "scale": scale.tolist()}


def dequantize(stored: np.ndarray, encoding: str, params: dict | None = None) -> np.ndarray:
    """Stored values (N, ...) -> float32 values of the same shape (computed in float64, then cast)."""
    if encoding in ("f32", "f16"):
        return stored.astype(np.float32)
    if encoding not in ENCODINGS and ac_bits(encoding) is None:
        raise ValueError(f"unknown encoding {encoding!r}")
    q = _channels(stored)
    with np.errstate(over="ignore"):  # numbers beyond float32 become inf, which readers refuse
        offset, scale = (np.asarray((params or {}).get(k), np.float32).astype(np.float64) for k in ("offset", "scale"))
    if offset.shape != (q.shape[1],) or scale.shape != (q.shape[1],):
        raise ValueError(f"{encoding} needs lists 'offset' and 'scale' of {q.shape[1]} numbers")
    with np.errstate(over="ignore", invalid="ignore"):  # values beyond float32 become inf or nan: refused
        return (offset + scale * q).astype(np.float32).reshape(stored.shape)


def error_bound(array, encoding: str):
    """The spec's bound on |dequantize(quantize(array)) - array|, broadcastable against (N, C).

    f32: 0.0; f16: per value (N, C); u8 / u16 / acB: per channel (C,) = scale / 2 + 2^-23 max |x|.
    """
    x = _channels(np.asarray(array, dtype=np.float32)).astype(np.float64)
    if encoding not in ENCODINGS and ac_bits(encoding) is None:
        raise ValueError(f"unknown encoding {encoding!r}")
    if encoding == "f32":
        return 0.0
    if encoding == "f16":
        return np.where(np.abs(x) >= 2.0**-14, np.abs(x) * 2.0**-11, 2.0**-25)
    _, scale = _affine(x.astype(np.float32), encoding)
    biggest = np.abs(x).max(axis=0) if x.shape[0] else np.zeros(x.shape[1])
    return scale / 2.0 + 2.0**-23 * biggest


# -- writing ------------------------------------------------------------------------------------


def written_version(kind: str, camera_models=(), segments=(), encodings=()) -> tuple[int, int]:
    """The version a writer puts in a file of `kind` whose cameras have `camera_models`, whose
    `segments` (Segment objects) are these and whose attributes use `encodings` (strings, see save):
    the lowest that holds it: 1.5 with an arithmetic-coded part (acB), 1.4 with another encoding than
    f32, f16, u8 and u16 (added in 1.4), 1.3 with a segment's context or crossfade (added in 1.3), 1.2
    with a camera other than a pinhole (added in 1.2), 1.1 for "sh" (added in 1.1), else 1.0, which
    every 1.x reader opens."""
    parts = [p.partition(":")[0].rpartition("/")[2] for e in encodings for p in e.split("+")]
    if any(ac_bits(p) is not None for p in parts):
        return (1, 5)
    if any(e not in ENCODINGS for e in encodings):
        return (1, 4)
    if any(s.crossfade_frames or any(s.context_frames) for s in segments):
        return (1, 3)
    if any(m != "pinhole" for m in camera_models):
        return (1, 2)
    return (1, 1) if kind == "sh" else (1, 0)


def encoding_parts(encoding: str) -> list[tuple[str, int]] | None:
    """The (encoding, channels) parts of a parts encoding "ENC:WIDTH+ENC:WIDTH..." (see save), None for
    an encoding of the whole array (one of PLAIN, "vq", "vq/ENC"); ValueError if unknown."""
    if ":" not in encoding:
        if not _plain(encoding) and not (encoding == "vq" or (encoding[:3] == "vq/" and _plain(encoding[3:]))):
            raise ValueError(f"unknown encoding {encoding!r} (expected one of {list(PLAIN)}, acB or acB-delta "
                             "(B = 1..16), 'vq', 'vq/ENCODING' or parts 'ENCODING:CHANNELS+...')")
        return None
    parts = []
    for text in encoding.split("+"):
        enc, _, width = text.partition(":")
        if encoding_parts(enc) is not None or not width.isdigit() or int(width) < 1:
            raise ValueError(f"bad part {text!r} of encoding {encoding!r} (expected ENCODING:CHANNELS)")
        parts.append((enc, int(width)))
    if len(parts) > MAX_PARTS:
        raise ValueError(f"encoding {encoding!r} has {len(parts)} parts, more than {MAX_PARTS}")
    return parts


def encode_array(values: np.ndarray, encoding: str, blob) -> dict:
    """The header's array entry for `values` (N, ...) written with `encoding` (see save); blob(bytes)
    stores a payload in the data section and returns its blob entry."""
    x = _channels(np.asarray(values, np.float32))
    head = {"shape": list(values.shape)}
    parts = encoding_parts(encoding)
    if parts is not None:
        if sum(w for _, w in parts) != x.shape[1]:
            raise ValueError(f"encoding {encoding!r} covers {sum(w for _, w in parts)} of {x.shape[1]} channels")
        starts = np.cumsum([0] + [w for _, w in parts])
        return {**head, "encoding": "parts",
                "parts": [encode_array(x[:, a:b], enc, blob) for (enc, _), a, b in zip(parts, starts, starts[1:])]}
    if encoding.startswith("vq"):
        if not np.all(np.isfinite(x)):
            raise ValueError("non-finite values cannot be written")
        rows, index = np.unique(x, axis=0, return_inverse=True)
        if len(rows) > MAX_CODEBOOK:
            raise ValueError(f"vq: {len(rows)} distinct values, more than a codebook's {MAX_CODEBOOK} rows "
                             "(cluster them first, as stg_train.convert.compress does)")
        if len(rows) == 0:  # no Gaussians: a codebook of one row of zeros
            rows = np.zeros((1, x.shape[1]), np.float32)
        dtype = np.dtype("u1") if len(rows) <= 256 else np.dtype("<u2")
        return {**head, "encoding": "vq", "codebook": encode_array(rows, encoding[3:] or "f32", blob),
                "data": blob(index.reshape(-1).astype(dtype).tobytes())}
    bits = ac_bits(encoding)
    if bits is not None:  # (1.5) B-bit integers, channel-major (differences), arithmetic-coded
        from . import range_coder

        stored, params = quantize(values, encoding.removesuffix("-delta"))
        symbols = np.ascontiguousarray(_channels(stored).T).astype(np.int64)
        if encoding.endswith("-delta"):
            symbols[:, 1:] = (symbols[:, 1:] - symbols[:, :-1]) % (1 << bits)
        return {**head, "encoding": encoding, **params, "data": blob(range_coder.encode(symbols, bits), "raw")}
    stored, params = quantize(values, DELTA.get(encoding, encoding))
    if encoding in DELTA:  # channel-major, each value minus the one before it (modulo 2^bits)
        stored = np.ascontiguousarray(_channels(stored).T)
        stored[:, 1:] -= stored[:, :-1].copy()
        stored = stored.reshape(-1).view(np.uint8).reshape(-1, stored.itemsize).T  # byte planes, low first
    return {**head, "encoding": encoding, **params, "data": blob(stored.tobytes())}


def dumps(model: Model, encodings: dict[str, str] | None = None, codec: str = "zlib", level: int = 6,
          provenance: dict | None = None) -> bytes:
    """The bytes of a .stg file holding `model`; see save()."""
    encodings = dict(encodings or {})
    unknown = set(encodings) - set(ATTRIBUTES)
    if unknown:
        raise ValueError(f"encodings: unknown attributes {sorted(unknown)}")
    for name, encoding in encodings.items():
        try:
            encoding_parts(encoding)
        except ValueError as e:
            raise ValueError(f"encodings: attribute {name!r}: {e}") from None
    if codec not in CODECS:
        raise ValueError(f"unknown codec {codec!r} (expected one of {CODECS})")
    model.validate()
    data = bytearray()

    def blob(payload: bytes, blob_codec: str = codec) -> dict:
        data.extend(bytes(-len(data) % ALIGN))
        payload = zlib.compress(payload, level) if blob_codec == "zlib" else payload
        entry = {"offset": len(data), "length": len(payload), "codec": blob_codec}
        data.extend(payload)
        return entry

    segments = []
    for i, seg in enumerate(model.segments):
        seg.validate()
        attributes = {}
        for name, values in seg.arrays().items():
            try:
                attributes[name] = encode_array(values, encodings.get(name, "f32"), blob)
            except ValueError as e:
                raise ValueError(f"segment {i}, attribute {name!r}: {e}") from None
        decoder = None if seg.decoder is None else {"activation": seg.activation,
                                                    "data": blob(bytes(seg.decoder), "raw")}
        entry = {"start_frame": seg.start_frame, "num_frames": seg.num_frames, "count": seg.count,
                 "position_degree": seg.position_degree, "rotation_degree": seg.rotation_degree,
                 "attributes": attributes, "decoder": decoder}
        if any(seg.context_frames):
            entry["context_frames"] = list(seg.context_frames)
        if seg.crossfade_frames:
            entry["crossfade_frames"] = seg.crossfade_frames
        segments.append(entry)
    bounds = None
    if model.bounds is not None:
        lo, hi = np.asarray(model.bounds, dtype=np.float64).reshape(2, 3).tolist()
        bounds = {"min": lo, "max": hi}
    provenance = model.provenance if provenance is None else provenance
    if not isinstance(provenance, dict):
        raise ValueError("provenance must be a dict")
    header = {"kind": model.kind, "fps": model.fps, "num_frames": model.num_frames, "segments": segments,
              "cameras": [c.to_dict() for c in model.cameras], "bounds": bounds, "provenance": provenance}
    text = _json(header).encode("utf-8")
    text += b" " * (-(PREFIX.size + len(text)) % ALIGN)  # the data section starts 8-byte aligned
    version = written_version(model.kind, [c.model for c in model.cameras], model.segments, encodings.values())
    body = PREFIX.pack(MAGIC, *version, len(text)) + text + bytes(data)
    return body + hashlib.sha256(body).digest()


def _json(value, indent: str = "") -> str:
    """JSON with one line per short object (an attribute with its blob) and per list of numbers."""
    flat = json.dumps(value, allow_nan=False)
    if len(flat) <= 120 or not isinstance(value, (dict, list)) or not value or (
            isinstance(value, list) and not any(isinstance(v, (dict, list)) for v in value)):
        return flat
    inner = indent + " "
    if isinstance(value, dict):
        lines = [f"{inner}{json.dumps(k)}: {_json(v, inner)}" for k, v in value.items()]
        return "{\n" + ",\n".join(lines) + "\n" + indent + "}"
    return "[\n" + ",\n".join(inner + _json(v, inner) for v in value) + "\n" + indent + "]"


def save(model: Model, path, encodings: dict[str, str] | None = None, codec: str = "zlib", level: int = 6,
         provenance: dict | None = None) -> None:
    """Write `model` to `path` atomically (temporary file in the same directory, fsync, rename).

    encodings: attribute name -> "f32" (default), "f16", "u8" or "u16"; (1.4) "u8-delta", "u16-delta"
    (u8 / u16 stored as differences, for sorted values); "vq/ENC": a codebook of the attribute's
    distinct rows (at most 65536; stored in ENC, one of those six, "vq" = "vq/f32")
    and an index per Gaussian; or parts "ENC:CHANNELS+ENC:CHANNELS...", consecutive channels each in
    one of the encodings above (e.g. "u16:3+vq/u8:9" for position coefficient 0 and the motion);
    (1.5) "acB", "acB-delta" (B = 1..16): B-bit fixed point, arithmetic-coded (stored raw), also as
    a part or a codebook.
    codec: "zlib" (level 0-9) or "raw" for the attribute blobs; the decoder is always stored raw. provenance overrides
    model.provenance. Raises ValueError (naming the attribute) for values the encoding cannot hold;
    on any error nothing is left at a new path.
    """
    write_atomic(path, dumps(model, encodings, codec, level, provenance))


# -- reading ------------------------------------------------------------------------------------


def load(path, limits: Limits = DEFAULT_LIMITS) -> Model:
    """Read a .stg file. Raises FormatError for any problem with its contents, including declarations
    beyond `limits` (OSError if unreadable)."""
    with open(path, "rb") as f:
        data = f.read()
    return loads(data, os.fsdecode(path), limits)


def loads(data: bytes, name: str = "<bytes>", limits: Limits = DEFAULT_LIMITS) -> Model:
    """Read a .stg file from bytes; `name` starts every FormatError message."""
    try:
        return _decode(memoryview(data).cast("B"), limits)
    except ValueError as e:  # includes json, UTF-8 and onnx_mlp errors
        raise FormatError(f"{name}: {e}") from e
    except (KeyError, TypeError, IndexError, OverflowError, RecursionError, struct.error, zlib.error) as e:
        raise FormatError(f"{name}: malformed file ({type(e).__name__}: {e})") from e


def _get(obj: dict, key: str, kind: type, where: str):
    """obj[key], which must exist and be an int (kind=int), a number (float), a str, a list or a dict."""
    if key not in obj:
        raise ValueError(f"{where}: missing field {key!r}")
    value = obj[key]
    if isinstance(value, bool) or not isinstance(value, (int, float) if kind is float else kind):
        raise ValueError(f"{where}: field {key!r} must be of type {kind.__name__}, got {type(value).__name__}")
    return value


def _decode(buf: memoryview, limits: Limits) -> Model:
    if len(buf) < PREFIX.size:
        raise ValueError(f"truncated: {len(buf)} bytes, shorter than the {PREFIX.size}-byte prefix")
    magic, major, minor, length = PREFIX.unpack_from(buf)
    if magic != MAGIC:
        raise ValueError("not an STG file (wrong magic bytes)")
    if major != VERSION[0]:
        raise ValueError(f"unsupported version {major}.{minor} (this reader reads {VERSION[0]}.x)")
    if length > MAX_HEADER:
        raise ValueError(f"header length {length} exceeds the {MAX_HEADER}-byte limit")
    start = PREFIX.size + length
    if len(buf) < start + 32:
        raise ValueError(f"truncated: header says {length} header bytes, file has {len(buf)} bytes in all")
    if hashlib.sha256(buf[:-32]).digest() != bytes(buf[-32:]):
        raise ValueError("checksum mismatch: the file is corrupt or truncated")
    header = json.loads(bytes(buf[PREFIX.size:start]).decode("utf-8"))
    if not isinstance(header, dict):
        raise ValueError("header is not a JSON object")
    section = buf[start:-32]
    kind = _get(header, "kind", str, "header")
    if kind not in KINDS:
        raise ValueError(f"header: unknown model kind {kind!r} in a version {major}.{minor} file (this reader, "
                         f"version {VERSION[0]}.{VERSION[1]}, renders {', '.join(KINDS)}; a newer one may read it)")
    entries = _get(header, "segments", list, "header")
    if not entries:
        raise ValueError("header: no segments")
    if len(entries) > limits.max_segments:
        raise ValueError(f"header: {len(entries)} segments, more than the reader's limit of {limits.max_segments}")
    layouts = [_layout(s, f"segment {i}", kind, limits) for i, s in enumerate(entries)]
    _check_sizes(layouts, len(buf), limits)
    segments = [_segment(s, f"segment {i}", layout, section) for i, (s, layout) in enumerate(zip(entries, layouts))]
    if _get(header, "num_frames", int, "header") != sum(s.num_frames for s in segments):
        raise ValueError(f"header: num_frames {header['num_frames']} is not the segments' total")
    cameras = []
    for i, c in enumerate(_get(header, "cameras", list, "header") if "cameras" in header else []):
        try:
            cameras.append(_camera(Camera.from_dict(c), limits))
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"camera {i}: invalid ({type(e).__name__}: {e})") from e
    bounds = header.get("bounds")
    if bounds is not None:
        lo, hi = (np.asarray(_get(bounds, k, list, "bounds"), dtype=np.float64) for k in ("min", "max"))
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite([lo, hi])):
            raise ValueError("bounds: min and max must be 3 finite numbers each")
        bounds = (tuple(lo.tolist()), tuple(hi.tolist()))
    provenance = header.get("provenance", {})
    if not isinstance(provenance, dict):
        raise ValueError("header: provenance must be an object")
    fps = _get(header, "fps", float, "header")
    if not 1e-3 <= fps <= 1e6:
        raise ValueError(f"header: fps {fps} is outside [0.001, 1000000]")
    return Model(kind, fps, segments, cameras, bounds, provenance)


def _camera(camera: Camera, limits: Limits) -> Camera:
    """`camera` when a renderer can use it: image sides within limits.max_image_side, focal lengths in
    [1e-3, 1e9] pixels, a finite principal point, a rotation (orthonormal within 1e-4, determinant +1) and
    a finite translation; ValueError otherwise."""
    side = limits.max_image_side
    if camera.width > side or camera.height > side:
        raise ValueError(f"image size {camera.width}x{camera.height} exceeds the reader's limit of {side} pixels")
    if not (1e-3 <= camera.fx <= 1e9 and 1e-3 <= camera.fy <= 1e9):
        raise ValueError(f"focal lengths fx={camera.fx:g}, fy={camera.fy:g} outside [1e-3, 1e9] pixels")
    if not (abs(camera.cx) <= 1e9 and abs(camera.cy) <= 1e9):
        raise ValueError(f"principal point ({camera.cx:g}, {camera.cy:g}) is not within 1e9 pixels")
    w2c = camera.world_to_camera
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: inf or nan, which fail the test
        rigid = (np.abs(w2c[:3, :3] @ w2c[:3, :3].T - np.eye(3)).max() <= 1e-4 and np.linalg.det(w2c[:3, :3]) > 0
                 and np.all(w2c[3] == [0, 0, 0, 1]) and np.abs(w2c[:3, 3]).max() <= 1e12)
    if not rigid:
        raise ValueError("world_to_camera is not a rigid transform (rotation, translation, last row 0 0 0 1)")
    return camera


def _layout(s, where: str, kind: str, limits: Limits) -> tuple:
    """(start_frame, num_frames, count, position_degree, rotation_degree, channels, extra) of a segment
    entry, checked against `limits` before any of its data is read; extra: the float32 values its
    arrays' codebooks take (1.4)."""
    if not isinstance(s, dict):
        raise ValueError(f"{where}: not a JSON object")
    start, frames, count, pdeg, qdeg = (_get(s, k, int, where) for k in
                                        ("start_frame", "num_frames", "count", "position_degree", "rotation_degree"))
    if min(start, count, pdeg, qdeg) < 0 or frames <= 0:
        raise ValueError(f"{where}: negative count/degree/start_frame or num_frames <= 0")
    if count > limits.max_gaussians:
        raise ValueError(f"{where}: {count} Gaussians, more than the reader's limit of {limits.max_gaussians} "
                         "(stg_runtime.format.Limits)")
    if max(pdeg, qdeg) > limits.max_degree:
        raise ValueError(f"{where}: polynomial degrees {pdeg}, {qdeg} beyond the reader's limit of {limits.max_degree}")
    if start + frames > limits.max_frames:
        raise ValueError(f"{where}: frames up to {start + frames}, beyond the reader's limit of {limits.max_frames}")
    attributes = _get(s, "attributes", dict, where)
    for name in ATTRIBUTES:
        if name not in attributes:
            raise ValueError(f"{where}: missing attribute {name!r}")
    channels = _feature_channels(attributes["features"], kind, f"{where}, attribute 'features'")
    extra = sum(_plan(attributes[name], attribute_shape(name, count, pdeg, qdeg, channels),
                      f"{where}, attribute {name!r}") for name in ATTRIBUTES)
    return start, frames, count, pdeg, qdeg, channels, extra


def _check_sizes(layouts: list, file_size: int, limits: Limits) -> None:
    """Refuse files whose arrays would decode to more than the limits allow (before decoding any)."""
    values = sum(math.prod(attribute_shape(name, count, pdeg, qdeg, channels))
                 for _, _, count, pdeg, qdeg, channels, _ in layouts for name in ATTRIBUTES)
    values += sum(layout[-1] for layout in layouts)  # codebooks
    allowed = limits.max_expansion * file_size + limits.expansion_allowance
    if 4 * values > allowed:
        raise ValueError(f"the arrays would take {4 * values} bytes in memory, more than the reader allows for a "
                         f"{file_size}-byte file ({allowed:.0f}; stg_runtime.format.Limits)")


def _segment(s: dict, where: str, layout: tuple, section: memoryview) -> Segment:
    start, frames, count, pdeg, qdeg, channels, _ = layout
    attributes = s["attributes"]
    arrays = {}
    for name in ATTRIBUTES:
        shape = attribute_shape(name, count, pdeg, qdeg, channels)
        arrays[name] = _array(attributes[name], shape, section, f"{where}, attribute {name!r}")
    decoder, activation = s.get("decoder"), "sigmoid"
    if decoder is not None:
        if not isinstance(decoder, dict):
            raise ValueError(f"{where}: decoder must be an object or null")
        activation = _get(decoder, "activation", str, f"{where}, decoder")
        if activation not in ACTIVATIONS:
            raise ValueError(f"{where}, decoder: activation must be one of {ACTIVATIONS}, got {activation!r}")
        decoder = bytes(_blob(_get(decoder, "data", dict, f"{where}, decoder"), section, None, f"{where}, decoder"))
        try:
            decoder = onnx_mlp.canonical(decoder)  # the MLP family only (formats/stg-v1.md, section 2)
        except ValueError as e:
            raise ValueError(f"{where}, decoder: {e}") from e
    context = s.get("context_frames", [0, 0])
    if (not isinstance(context, list) or len(context) != 2
            or not all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= MAX_SPAN for c in context)):
        raise ValueError(f"{where}: context_frames must be a list of two integers in [0, {MAX_SPAN}]")
    crossfade = s.get("crossfade_frames", 0)
    if isinstance(crossfade, bool) or not isinstance(crossfade, int) or not 0 <= crossfade <= MAX_SPAN:
        raise ValueError(f"{where}: crossfade_frames must be an integer in [0, {MAX_SPAN}]")
    try:
        return Segment(start, frames, decoder=decoder, activation=activation, context_frames=tuple(context),
                       crossfade_frames=crossfade, **arrays)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from e


def _feature_channels(spec, kind: str, where: str) -> int:
    """The features' channel count: fixed by the kind (lite 3, full 9), or for "sh" the one the array's
    shape declares, which must be 3 (d+1)^2 for an SH degree d in 0..3."""
    if kind != "sh":
        return FEATURE_CHANNELS[kind]
    shape = spec.get("shape") if isinstance(spec, dict) else None
    allowed = allowed_channels(kind)
    if not (isinstance(shape, list) and len(shape) == 2 and type(shape[1]) is int and shape[1] in allowed):
        raise ValueError(f"{where}: shape {shape} is not (count, C) with C one of {allowed} "
                         "(3 (d+1)^2 SH coefficients, degree d in 0..3)")
    return shape[1]


def _plan(spec, shape: tuple, where: str, inside: str = "") -> int:
    """Check an array entry's structure against `shape` before any of it is decoded: its shape, its
    encoding, (1.4) a "vq" codebook's shape and a "parts" entry's parts. Returns the float32 values the
    decoding takes beyond the array itself (codebooks). inside: "codebook" or "part" for a nested entry."""
    if not isinstance(spec, dict):
        raise ValueError(f"{where}: not a JSON object")
    if _get(spec, "shape", list, where) != list(shape):
        raise ValueError(f"{where}: shape {spec['shape']} disagrees with count and degrees, expected {list(shape)}")
    encoding = _get(spec, "encoding", str, where)
    channels = math.prod(shape[1:])
    if _plain(encoding):
        return 0
    if encoding == "vq" and inside != "codebook":
        book = _get(spec, "codebook", dict, where)
        rows = book["shape"][0] if isinstance(book.get("shape"), list) and book["shape"] else None
        if type(rows) is not int or not 1 <= rows <= MAX_CODEBOOK:
            raise ValueError(f"{where}: a codebook's shape must be [K, {channels}] with K in [1, {MAX_CODEBOOK}], "
                             f"got {book.get('shape')}")
        _plan(book, (rows, channels), f"{where}, codebook", "codebook")
        return rows * channels
    if encoding == "parts" and not inside:
        parts = _get(spec, "parts", list, where)
        if not 1 <= len(parts) <= MAX_PARTS:
            raise ValueError(f"{where}: {len(parts)} parts, expected 1 to {MAX_PARTS}")
        extra, covered = 0, 0
        for j, part in enumerate(parts):
            width = part.get("shape") if isinstance(part, dict) else None
            width = width[1] if isinstance(width, list) and len(width) == 2 else None
            if type(width) is not int or width < 1:
                raise ValueError(f"{where}, part {j}: shape must be [{shape[0]}, channels >= 1]")
            covered += width
            if covered > channels:
                break
            extra += _plan(part, (shape[0], width), f"{where}, part {j}", "part")
        if covered != channels:
            raise ValueError(f"{where}: the parts cover {covered} channels, the array has {channels}")
        return extra
    raise ValueError(f"{where}: unknown encoding {encoding!r}" + (f" (not allowed in a {inside})" if inside else ""))


def _array(spec, shape: tuple, section: memoryview, where: str) -> np.ndarray:
    """An array entry {"shape", "encoding", ...} (checked by _plan) -> float32 array of `shape`."""
    values = _values(spec, shape, section, where)
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{where}: decoded values are not all finite")
    return values


def _values(spec: dict, shape: tuple, section: memoryview, where: str) -> np.ndarray:
    encoding, channels = spec["encoding"], math.prod(shape[1:])
    bits = ac_bits(encoding)
    if bits is not None:  # (1.5) arithmetic-coded B-bit integers, channel-major
        from . import range_coder

        data = _blob(_get(spec, "data", dict, where), section, None, where)
        try:
            symbols = range_coder.decode(data, channels, shape[0], bits)
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from e
        if encoding.endswith("-delta"):
            symbols = np.cumsum(symbols, axis=1, dtype=np.uint16) & np.uint16((1 << bits) - 1)
        try:
            return dequantize(np.ascontiguousarray(symbols.T).reshape(shape), encoding.removesuffix("-delta"), spec)
        except (ValueError, TypeError) as e:
            raise ValueError(f"{where}: {e}") from e
    if encoding == "parts":  # (1.4) consecutive channels, each part decoded into its place
        out, at = np.empty((shape[0], channels), np.float32), 0
        for j, part in enumerate(spec["parts"]):
            width = part["shape"][1]
            out[:, at:at + width] = _values(part, (shape[0], width), section, f"{where}, part {j}")
            at += width
        return out.reshape(shape)
    if encoding == "vq":  # (1.4) codebook rows picked by an index per value
        rows = spec["codebook"]["shape"][0]
        book = _values(spec["codebook"], (rows, channels), section, f"{where}, codebook")
        dtype = np.dtype("u1") if rows <= 256 else np.dtype("<u2")
        index = np.frombuffer(_blob(_get(spec, "data", dict, where), section, shape[0] * dtype.itemsize, where), dtype)
        if index.size and int(index.max()) >= rows:
            raise ValueError(f"{where}: index {int(index.max())} beyond the codebook's {rows} rows")
        return book[index].reshape(shape)
    base = DELTA.get(encoding, encoding)
    size = math.prod(shape) * ENCODINGS[base].itemsize
    stored = np.frombuffer(_blob(_get(spec, "data", dict, where), section, size, where), ENCODINGS[base])
    if encoding in DELTA:  # (1.4) byte planes of differences -> running sums (modulo 2^bits) per channel
        planes = np.frombuffer(stored.tobytes(), np.uint8).reshape(stored.itemsize, -1)
        stored = np.ascontiguousarray(planes.T).view(stored.dtype).reshape(channels, shape[0])
        stored = np.cumsum(stored, axis=1, dtype=stored.dtype).T
    try:
        return dequantize(stored.reshape(shape), base, spec)
    except (ValueError, TypeError) as e:
        raise ValueError(f"{where}: {e}") from e


def encoding_of(spec: dict) -> str:
    """The writer's encoding string (see save) of a valid file's array entry: "u16", "vq/u8",
    "u16:3+vq/u8:9", ..."""
    if spec["encoding"] == "parts":
        return "+".join(f"{encoding_of(p)}:{p['shape'][1]}" for p in spec["parts"])
    if spec["encoding"] == "vq":
        return "vq/" + spec["codebook"]["encoding"]
    return spec["encoding"]


def _blob(spec: dict, section: memoryview, size: int | None, where: str):
    """The decoded bytes of a blob {"offset", "length", "codec"}; `size` is the decoded size it must have
    (None: any, and the blob must be raw)."""
    offset, length = _get(spec, "offset", int, where), _get(spec, "length", int, where)
    codec = _get(spec, "codec", str, where)
    if offset < 0 or length < 0 or offset + length > len(section):
        raise ValueError(f"{where}: blob [{offset}, {offset + length}) lies outside the "
                         f"{len(section)}-byte data section")
    data = section[offset:offset + length]
    if codec not in (CODECS if size is not None else ("raw",)):  # sizes not implied (decoders, acB): raw only
        raise ValueError(f"{where}: unsupported codec {codec!r}")
    if codec == "zlib":
        inflater = zlib.decompressobj()
        data = inflater.decompress(data, max(size, 1))  # never more than `size` bytes (0 means no limit)
        if not inflater.eof:
            data += inflater.decompress(inflater.unconsumed_tail, 1)
        if not inflater.eof or inflater.unused_data:
            raise ValueError(f"{where}: zlib data does not end after {size} bytes (longer, cut short or with junk)")
    if size is not None and len(data) != size:
        raise ValueError(f"{where}: blob holds {len(data)} bytes, shape and encoding imply {size}")
    return data
