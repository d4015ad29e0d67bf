#!/usr/bin/env python
"""Fuzz the readers with mutated files and print what happened to them.

    python tools/fuzz.py [--stg N] [--ply N] [--seed S] [--timeout SECONDS] [--vectors A,B]

.stg files: the test vectors (formats/vectors/) mutated in their JSON header (a value replaced by one
of a pool of hostile values, or a key deleted), in their data section, in their decoder's bytes or
anywhere, then sealed with a valid checksum so that every check behind it is reached. Each is loaded
(stg_runtime.format.load), and what loads is rendered with Player(device="cpu") from its first camera
(at most 64 pixels wide) at its first and middle frame. Allowed: FormatError at load, RenderError at
render. PLYs: a 3DGS PLY and a reference-implementation PLY, binary and ASCII, with their header lines
or bytes mutated or the file cut, read by read_ply, import_3dgs_ply and read_reference_ply. Allowed:
PLYError. Anything else (another exception, a render slower than --timeout) is printed and counted as
unexpected; the exit code is 1 when there is any. tests/test_fuzz.py runs a moderate number in CI.
"""
from __future__ import annotations

import argparse
import collections
import json
import math
import re
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

from craft import seal, split
from stg_runtime import Camera, FormatError, Player, RenderError
from stg_runtime import format as stg_format
from stg_runtime.demo import random_model
from stg_train.convert.gaussians3d import export_ply, import_3dgs_ply
from stg_train.convert.ply import PLYError, read_ply, write_ply
from stg_train.convert.reference import FULL, read_reference_ply

ROOT = Path(__file__).resolve().parent.parent
POOL = [None, True, False, 0, 1, -1, 2, 3, 7, 255, 256, 65535, 2 ** 31 - 1, 2 ** 31, 2 ** 32, 2 ** 53, 2 ** 63 - 1,
        2 ** 63, 2 ** 64, 10 ** 20, -10 ** 20, 0.5, -0.0, 1e-300, 5e-324, 1e300, 1.7e308, math.nan, math.inf,
        -math.inf, "", "f16", "f32", "u8", "u16", "zlib", "raw", "x" * 1000, "full", "lite", "sh", "clamp", [],
        "vq", "parts", "u8-delta", "u16-delta", 65536, 65537, [65536, 9], {"shape": [1, 1], "encoding": "f32"},
        [0], [1] * 17, [1e300] * 3, {}, {"offset": 0, "length": 0, "codec": "raw"}]


class Timeout(Exception):
    pass


def _alarm(signum, frame):
    raise Timeout


def _leaves(node, found):
    """Every (container, key) pair under a JSON value."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, value in items:
        found.append((node, key))
        _leaves(value, found)
    return found


def mutate_stg(data: bytes, rng: np.random.Generator) -> tuple[str, bytes]:
    """(kind of mutation, sealed file)."""
    header, section, version = split(data)
    how = str(rng.choice(["json value", "json value", "json delete", "section bytes", "decoder bytes", "any bytes"]))
    if how.startswith("json"):
        leaves = _leaves(header, [])
        container, key = leaves[rng.integers(len(leaves))]
        if how == "json delete":
            del container[key]
        else:
            old = container[key]
            value = POOL[rng.integers(len(POOL))]
            if isinstance(old, (int, float)) and not isinstance(old, bool) and rng.random() < 0.3:
                value = old * [-1, 2, 1000][rng.integers(3)] + [-1, 0, 1][rng.integers(3)]
            container[key] = value
        return how, seal(json.dumps(header).encode(), section, version)
    body = bytearray(section)
    if how == "decoder bytes":
        decoders = [s["decoder"]["data"] for s in header["segments"] if s.get("decoder")]
        if not decoders:
            how = "section bytes"
        else:
            blob = decoders[rng.integers(len(decoders))]
            for _ in range(rng.integers(1, 5)):
                body[blob["offset"] + rng.integers(blob["length"])] = rng.integers(256)
            return how, seal(header, bytes(body), version)
    if how == "section bytes":
        for _ in range(rng.integers(1, 9)):
            body[rng.integers(len(body))] = rng.integers(256)
        return how, seal(header, bytes(body), version)
    text = bytearray(json.dumps(header).encode())
    whole = text + body
    for _ in range(rng.integers(1, 5)):
        whole[rng.integers(len(whole))] = rng.integers(256)
    return how, seal(bytes(whole[:len(text)]), bytes(whole[len(text):]), version)


def _camera(model) -> Camera:
    if model.cameras:
        c = model.cameras[0]
        width = min(c.width, 64)
        return c.resized(width, max(1, round(c.height * width / c.width)))
    return Camera.look_at([0, 0, 0], [0, 0, 4], [0, -1, 0], 50.0, 32, 24)


def fuzz_stg(count: int, rng, timeout: float, outcomes: collections.Counter, unexpected: list,
             vectors: list[str] | None = None) -> None:
    paths = sorted((ROOT / "formats" / "vectors").glob("*.stg"))
    bases = [p.read_bytes() for p in paths if not vectors or p.stem in vectors]
    if not bases:
        raise SystemExit(f"fuzz.py: no test vector named {', '.join(vectors)} in formats/vectors/")
    for k in range(count):
        how, data = mutate_stg(bases[k % len(bases)], rng)
        stage = "load"
        try:
            model = stg_format.loads(data, "fuzz.stg")
            stage = "render"
            signal.alarm(math.ceil(timeout))
            player = Player(model, device="cpu")
            camera = _camera(model)
            for frame in (model.start_frame, model.start_frame + model.num_frames // 2):
                player.render(camera, frame / model.fps)
            outcomes["stg: loads and renders"] += 1
        except FormatError as e:
            outcomes["stg: FormatError: " + _reason(str(e))] += 1
        except RenderError:
            outcomes["stg: RenderError"] += 1
        except Exception as e:  # noqa: BLE001 - anything else is what the fuzzer looks for
            unexpected.append(f"stg ({how}) at {stage}: {type(e).__name__}: {e}\n{traceback.format_exc(limit=3)}")
        finally:
            signal.alarm(0)


def _reason(message: str) -> str:
    """The kind of a reader's message: the file name, places (segment 3, attribute 'x'), values and
    details in parentheses left out, shortened."""
    text = message.split(": ", 1)[-1]
    text = re.sub(r"^(segment \d+|camera \d+|header|bounds)(, (attribute '[^']*'|decoder))?: ", "", text)
    text = re.sub(r"\(.*|0x[0-9a-f]+|'[^']*'|\"[^\"]*\"|\[[^\]]*\]|-?\d[\d.e+-]*", "_", text)
    return re.sub(r"\s+", " ", text).strip()[:56]


def _ply_bases(folder: Path) -> list[Path]:
    rng = np.random.default_rng(0)
    model = random_model(40, "lite", seed=1)
    export_ply(model, folder / "gaussians.ply", t=0.0)
    props, _ = read_ply(folder / "gaussians.ply")
    write_ply(folder / "gaussians_ascii.ply", props, fmt="ascii")
    reference = {name: rng.standard_normal(30).astype(np.float32) for name in FULL}
    write_ply(folder / "reference.ply", reference)
    write_ply(folder / "reference_ascii.ply", reference, fmt="ascii")
    return [folder / n for n in ("gaussians.ply", "gaussians_ascii.ply", "reference.ply", "reference_ascii.ply")]


def mutate_ply(data: bytes, rng: np.random.Generator) -> tuple[str, bytes]:
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines, body = data[:end].decode("ascii").split("\n")[:-1], bytearray(data[end:])
    how = str(rng.choice(["header line", "header line", "body bytes", "cut"]))
    if how == "header line":  # lines[0] is "ply", lines[-1] "end_header"
        i = int(rng.integers(1, len(lines) - 1))
        words = lines[i].split()
        choice = rng.integers(4)
        if choice == 0 and words[0] == "element":
            words[2] = str([0, 1, 10 ** 9, 10 ** 20, 2 ** 63, int(words[2]) + 1][rng.integers(6)])
            lines[i] = " ".join(words)
        elif choice == 1 and words[0] == "property":
            words[1] = str(rng.choice(["double", "uchar", "int", "list", "float128", "char"]))
            lines[i] = " ".join(words)
        elif choice == 2:
            lines.insert(i, lines[i])
        else:
            del lines[i]
        return how, ("\n".join(lines) + "\n").encode("ascii") + bytes(body)
    if how == "body bytes" and body:
        for _ in range(rng.integers(1, 9)):
            body[rng.integers(len(body))] = rng.integers(256)
        return how, data[:end] + bytes(body)
    return "cut", data[:int(rng.integers(1, len(data)))]


def fuzz_ply(count: int, rng, outcomes: collections.Counter, unexpected: list) -> None:
    with tempfile.TemporaryDirectory(prefix="stg_fuzz_") as tmp:
        folder = Path(tmp)
        bases = [p.read_bytes() for p in _ply_bases(folder)]
        path = folder / "fuzz.ply"
        readers = (read_ply, import_3dgs_ply, read_reference_ply)
        for k in range(count):
            how, data = mutate_ply(bases[k % len(bases)], rng)
            path.write_bytes(data)
            reader = readers[k % len(readers)]
            try:
                reader(path)
                outcomes[f"ply: {reader.__name__} reads it"] += 1
            except PLYError as e:
                outcomes["ply: PLYError: " + _reason(str(e))] += 1
            except Exception as e:  # noqa: BLE001
                unexpected.append(f"ply ({how}) in {reader.__name__}: {type(e).__name__}: {e}\n"
                                  f"{traceback.format_exc(limit=3)}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stg", type=int, default=20000, help="mutated .stg files (default %(default)s)")
    ap.add_argument("--ply", type=int, default=20000, help="mutated PLYs (default %(default)s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=20.0, help="seconds a render may take (default %(default)s)")
    ap.add_argument("--vectors", type=lambda v: [n for n in v.split(",") if n], default=None, metavar="A,B",
                    help="mutate only these test vectors (names without .stg; default all)")
    args = ap.parse_args(argv)
    signal.signal(signal.SIGALRM, _alarm)
    rng = np.random.default_rng(args.seed)
    outcomes: collections.Counter = collections.Counter()
    unexpected: list = []
    start = time.perf_counter()
    fuzz_stg(args.stg, rng, args.timeout, outcomes, unexpected, args.vectors)
    fuzz_ply(args.ply, rng, outcomes, unexpected)
    print(f"{args.stg} .stg files and {args.ply} PLYs in {time.perf_counter() - start:.0f} s (seed {args.seed})")
    for what, n in sorted(outcomes.items(), key=lambda kv: (-kv[1], kv[0])):
        print(f"{n:7d}  {what}")
    for item in unexpected[:20]:
        print("UNEXPECTED:", item)
    print(f"unexpected: {len(unexpected)}")
    return 1 if unexpected else 0


if __name__ == "__main__":
    sys.exit(main())
