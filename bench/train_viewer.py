#!/usr/bin/env python
"""How much `stg-train --viewer` slows training: wall-clock seconds of the same training run with and
without the training viewer, alternated.

    python bench/train_viewer.py [--iterations 150] [--repeats 2] [--every 5] [--client browser|socket]
                                 [--no-browser]

Trains the demo's synthetic scene (stg_train.pipeline.DEMO_SCENE, the demo's settings, --iterations
steps; the scene is written once to --data) with Trainer.train, timing steps 2..N, once without
and once with a TrainingViewer whose snapshot interval is --every seconds, --repeats times in turn.
With the viewer, a client of bench/view.py is connected and rests on training camera 0, so every
snapshot is rendered and sent, as for a user watching: `--client browser` (the default), headless
chromium on the same cores (selenium; Debian's chromium and chromium-driver); `--client socket`, viser's
protocol from Python, standing for a browser on another machine; `--no-browser`, none.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from stg_train.data import load_dataset
from stg_train.pipeline import DEMO_TRAINING, ensure_demo_scene
from stg_train.trainer import Trainer, TrainConfig
from stg_train.viewer import TrainingViewer


def run(dataset, config: TrainConfig, viewer: bool, every: float, client_name: str | None) -> tuple[float, int, float]:
    """(wall-clock seconds of steps 2..N of Trainer.train, pictures sent, seconds of viewer work: its
    snapshots and status on the training thread plus its renders) for one run. The clock starts after
    the first step, once the viewer serves and the client (None: no client) has connected."""
    trainer = Trainer(dataset, config)
    viewer_callback = TrainingViewer(port=0, every=every, quiet=True) if viewer else None
    client, start, sent, work = None, [], 0, []

    def callback(t):
        nonlocal client, sent
        if viewer_callback is not None:
            viewer_callback(t)
            if client_name and client is None:
                import view  # bench/view.py, beside this file
                client = view.CLIENTS[client_name](viewer_callback.viewer, 640, 360)
                while not viewer_callback.viewer.streams:
                    time.sleep(0.1)
            if t.step == config.iterations:
                streams = viewer_callback.viewer.streams.values()
                sent = sum(s.stats.sent for s in streams)
                work.append(viewer_callback.seconds + sum(s.stats.render_total for s in streams))
        if not start:
            start.append(time.perf_counter())

    try:
        trainer.train(progress=False, callback=callback)
        seconds = time.perf_counter() - start[0]
    finally:
        if client is not None:
            client.close()
        if viewer_callback is not None:
            viewer_callback.close()
    return seconds, sent, work[0] if work else 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--every", type=float, default=5.0, help="seconds between the viewer's snapshots")
    ap.add_argument("--client", choices=["browser", "socket"], default="browser",
                    help="the client connected: headless chromium, or viser's protocol from Python")
    ap.add_argument("--no-browser", action="store_true", help="no client connected")
    ap.add_argument("--data", default=os.path.join(tempfile.gettempdir(), "stg-bench-demo-scene"))
    args = ap.parse_args()
    dataset = load_dataset(ensure_demo_scene(Path(args.data)), show_progress=False)
    config = TrainConfig(**{**DEMO_TRAINING, "iterations": args.iterations})
    client = None if args.no_browser else args.client
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}; demo scene, {args.iterations} steps, "
          f"snapshot every {args.every:g} s, client: {client or 'none'}")
    times = {False: [], True: []}
    for _ in range(args.repeats):
        for viewer in (False, True):
            seconds, sent, work = run(dataset, config, viewer, args.every, client)
            times[viewer].append(seconds)
            print(f"{'with' if viewer else 'without':<8} viewer: {seconds:7.1f} s" +
                  (f", {sent} pictures sent, viewer work {work:.1f} s ({100 * work / seconds:.1f}% of the run)"
                   if viewer else ""))
    base, with_viewer = np.median(times[False]), np.median(times[True])
    print(f"median: {base:.1f} s without, {with_viewer:.1f} s with the viewer: {100 * (with_viewer / base - 1):+.1f}%")


if __name__ == "__main__":
    main()
