#!/usr/bin/env python
"""Feasibility probe (docs/web.md, "What remains"): could a WebAssembly SIMD compositor in the page
composite the benchmark frame as fast as the CPU `Player`'s numba compositor?

    npm install --prefix /tmp/wabt wabt          # once; the probe assembles its WAT with wabt
    WABT=/tmp/wabt/node_modules/wabt python bench/web_wasm_probe.py [--gaussians 100000] [--size 640x360]
                                                                    [--rounds 15] [--dir /tmp/stg-wasm-probe]

This script renders one frame of stg_runtime.demo.like_trained_model (lite) at 0.55 of its span with
the numba splatter's own steps (splat_cpu: _project, sort_by_depth, bin_tiles), dumps what its
compositor reads (the 64-byte records, the per-tile depth-ordered lists, the tile order), its outputs
and the segment's arrays as raw .bin files into --dir, and starts `node bench/web_wasm_probe.mjs
--serve DIR`, which checks its WASM SIMD compositors' images against the dump (standard SIMD, and
relaxed SIMD's fused multiply-add where node has it) and its plain-JS front end's tile lists, then
times them on request. Then, in rounds, interleaved in this one session (numba and WASM alternate):
numba's compositor (splat_cpu._composite) on 1 thread and on 2 (numba.set_num_threads), the WASM
compositor on 1 thread and on 2 worker threads (shared memory), handing the records to a worker
(postMessage, a copy) and an RGBA image back, the JS front end (time evaluation, projection, sort,
binning; one thread), and the CPU Player's own steps before compositing and whole Player.render, on
2 threads and on 1. It prints min and median of each and the per-round ratios, with the machine and
its load average.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numba
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from stg_runtime import Player  # noqa: E402
from stg_runtime import splat_cpu as sc  # noqa: E402
from stg_runtime.demo import like_trained_model  # noqa: E402
from stg_runtime.projection import camera_params  # noqa: E402
from stg_runtime.spec import BLUR, NEAR  # noqa: E402
from stg_runtime.timeeval import evaluate  # noqa: E402

TILE = 16


def steps(g, camera):
    """splat_cpu.rasterize's steps before compositing, for lite features (C = 3): what _composite reads.
    Returns packed, tile_start, tile_ids, tile_order, tiles_x."""
    f32 = lambda x, shape: np.ascontiguousarray(np.asarray(x, np.float32).reshape(shape))  # noqa: E731
    means = f32(g.means, (-1, 3))
    m = means.shape[0]
    W, H = camera.width, camera.height
    packed = sc._aligned_empty((m, sc._PACKED))
    tiles = np.empty((m, 4), np.int32)
    depth = np.empty(m, np.float64)
    with numba.parallel_chunksize(2048):
        sc._project(means, f32(g.quats, (m, 4)), f32(g.scales, (m, 3)), f32(g.opacities, (m,)),
                    f32(g.features, (m, -1)), camera_params(camera), W, H, TILE, packed, tiles, depth)
    order = sc.sort_by_depth(tiles, depth)
    tiles_x, tiles_y = -(-W // TILE), -(-H // TILE)
    tile_start, tile_ids, tile_order = sc.bin_tiles(order, tiles, tiles_x, tiles_y)
    return packed, tile_start, tile_ids, tile_order, tiles_x


def composite(packed, tile_start, tile_ids, tile_order, tiles_x, W, H):
    """splat_cpu._composite for C = 3 (as rasterize calls it) with numba's current thread count."""
    out_f = np.empty((H, W, 3), np.float32)
    out_a = np.empty((H, W), np.float32)
    out_d = np.empty((H, W), np.float32)
    n_tiles = tile_start.shape[0] - 1
    sc._composite(packed, np.empty((packed.shape[0], 0), np.float32), 3, tile_start, tile_ids, tile_order,
                  TILE, tiles_x, W, H, max(1, min(numba.get_num_threads(), n_tiles)), out_f.reshape(-1),
                  out_a.reshape(-1), out_d.reshape(-1))
    return out_f, out_a, out_d


def stats(xs, highest=False):
    """min and median of xs (and max with highest)."""
    top = f"  max {max(xs):5.2f}" if highest else ""
    return f"min {min(xs):7.2f}  median {float(np.median(xs)):7.2f}{top}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--dir", default="/tmp/stg-wasm-probe")
    args = ap.parse_args(argv)
    from machine import describe
    W, H = map(int, args.size.split("x"))
    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    model = like_trained_model(args.gaussians, width=W, height=H, kind="lite")
    player = Player(model, device="cpu")
    camera = player.cameras[0]
    t = player.start_time + 0.55 * player.duration
    segment, tau = model.segment_at(t)
    g = evaluate(segment, tau)
    threads = numba.get_num_threads()
    packed, tile_start, tile_ids, tile_order, tiles_x = steps(g, camera)  # compiles, warms up
    ref_f, ref_a, ref_d = composite(packed, tile_start, tile_ids, tile_order, tiles_x, W, H)
    full_f, full_a, _ = sc.rasterize(g.means, g.quats, g.scales, g.opacities, g.features, camera)
    assert np.array_equal(ref_f, full_f) and np.array_equal(ref_a, full_a), "steps() is not rasterize's"
    for name, a, dtype in [("packed", packed, np.float32), ("tile_start", tile_start, np.int32),
                           ("tile_ids", tile_ids, np.int32), ("tile_order", tile_order, np.int32),
                           ("ref_f", ref_f, np.float32), ("ref_a", ref_a, np.float32), ("ref_d", ref_d, np.float32)]:
        np.ascontiguousarray(a, dtype).tofile(out / f"{name}.bin")
    for name in ("opacity", "t_center", "t_scale", "position", "rotation", "scale", "features"):  # for the JS front end
        np.ascontiguousarray(getattr(segment, name), np.float32).tofile(out / f"seg_{name}.bin")
    (out / "meta.json").write_text(json.dumps({
        "width": W, "height": H, "tile": TILE, "tiles_x": tiles_x, "records": int(packed.shape[0]),
        "entries": int(tile_ids.shape[0]), "tau": float(tau), "camera": list(camera_params(camera)),
        "gaussians": int(segment.opacity.shape[0]), "position_terms": int(segment.position.shape[1]),
        "rotation_terms": int(segment.rotation.shape[1]), "near": NEAR, "blur": BLUR}))
    print(f"machine: {describe()}; numba threads {threads}")
    print(f"frame: {args.gaussians} Gaussians (lite), {W}x{H}, t = {t:.3f} s: {g.means.shape[0]} after the opacity "
          f"floor, {tile_ids.shape[0]} tile-list entries in {tile_start.shape[0] - 1} tiles")
    wabt = os.environ.get("WABT", "/tmp/wabt/node_modules/wabt")
    flags = ["--no-liftoff"]  # the optimised code from the first call (a page's kernel tiers up within frames)
    if subprocess.run(["node", "--experimental-wasm-relaxed-simd", "-e", "0"], capture_output=True).returncode == 0:
        flags.append("--experimental-wasm-relaxed-simd")  # node 20: relaxed SIMD (Chromium ships it)
    node = subprocess.Popen(["node", *flags, str(ROOT / "bench" / "web_wasm_probe.mjs"), "--serve", str(out)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env={**os.environ, "WABT": wabt})

    def ask(command: str) -> str:
        node.stdin.write(command + "\n")
        node.stdin.flush()
        return node.stdout.readline().strip()

    kinds = ask("kinds").split()
    check = ask("check")
    print("WASM check:", check)
    if "FAIL" in check:
        raise SystemExit("the WASM compositor's image or the JS front end's lists differ from the Player's")
    wasm = [f"c1 {k}" for k in kinds] + [f"c2 {k}" for k in kinds] + ["copy", "front"]
    names = {"c1 simd": "WASM 1 thread (standard SIMD)", "c1 fma": "WASM 1 thread (relaxed SIMD FMA)",
             "c2 simd": "WASM 2 workers (standard SIMD)", "c2 fma": "WASM 2 workers (relaxed SIMD FMA)",
             "copy": "records + lists to a worker, image back", "front": "JS front end (1 thread)"}
    for _ in range(2):  # warm-up of every path
        for c in wasm:
            ask(c)
    figures: dict = {k: [] for k in ["numba 2 threads", "numba 1 thread", *(names[c] for c in wasm),
                                      "Player steps before compositing (2 threads)", "Player steps before compositing (1 thread)",
                                      "Player.render (2 threads)", "Player.render (1 thread)"]}

    def numba_composite(n: int) -> float:
        numba.set_num_threads(n)
        s = time.perf_counter()
        composite(packed, tile_start, tile_ids, tile_order, tiles_x, W, H)
        numba.set_num_threads(threads)
        return 1e3 * (time.perf_counter() - s)

    loads = [os.getloadavg()[0]]
    times = np.linspace(player.start_time, player.start_time + 0.9 * player.duration, args.rounds)
    for r in range(args.rounds):  # A, B, A, B...: numba and WASM alternate
        for c in wasm:
            if c.startswith("c1"):
                figures["numba 1 thread"].append(numba_composite(1))
            elif c.startswith("c2"):
                figures["numba 2 threads"].append(numba_composite(threads))
            figures[names[c]].append(float(ask(c)))
        for n, label in ((threads, "2 threads"), (1, "1 thread")):
            numba.set_num_threads(n)
            s = time.perf_counter()
            steps(evaluate(segment, tau), camera)
            figures[f"Player steps before compositing ({label})"].append(1e3 * (time.perf_counter() - s))
            s = time.perf_counter()
            player.render(camera, float(times[r]))
            figures[f"Player.render ({label})"].append(1e3 * (time.perf_counter() - s))
        numba.set_num_threads(threads)
        loads.append(os.getloadavg()[0])
    node.stdin.close()
    node.wait()
    print(f"{args.rounds} rounds, load average {min(loads):.2f} .. {max(loads):.2f}; ms:")
    for name, xs in figures.items():
        print(f"  {name:45} {stats(xs)}")
    print("per-round ratios (WASM / numba; numba 1 thread's samples pair with the 1-thread kernels in turn):")
    one = figures["numba 1 thread"]
    two = figures["numba 2 threads"]
    for i, k in enumerate(kinds):
        pairs1 = one[i::len(kinds)]
        pairs2 = two[i::len(kinds)]
        print(f"  {names['c1 ' + k]} / numba 1 thread: {stats([w / n for w, n in zip(figures[names['c1 ' + k]], pairs1)])}")
        print(f"  {names['c2 ' + k]} / numba 2 threads: {stats([w / n for w, n in zip(figures[names['c2 ' + k]], pairs2)])}")
    print("projected page frame, per round: the JS front end + WASM compositing (+ the records to a worker and the image "
          "back, for 2 workers); ms, and its speed against the Player's (Player.render's ms / the page's; >= 1: as fast):")
    front = figures[names["front"]]
    for k in kinds:
        for c, extra in ((f"c1 {k}", [0.0] * args.rounds), (f"c2 {k}", figures[names["copy"]])):
            page = [f + w + e for f, w, e in zip(front, figures[names[c]], extra)]
            ratios = "; ".join(f"vs Player {label}: {stats([q / p for p, q in zip(page, figures[f'Player.render ({label})'])], True)}"
                               for label in ("2 threads", "1 thread"))
            print(f"  {'1 worker' if c.startswith('c1') else '2 workers'}, {k}: {stats(page)} ms; {ratios}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
