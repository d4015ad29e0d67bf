"""How long each command takes to answer `--help` and a bad argument (a fresh Python process each time,
as a user's shell starts it).

    python bench/cli_help.py [--repeat 7] [--against OTHER_CHECKOUT]

Prints the median wall time per command and case; with --against, the same for another checkout
(e.g. `git worktree add /tmp/old <commit>`), measured interleaved in the same run, and the ratio.
docs/performance.md has the figures.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = {"stg-train": "stg_train.cli.train", "stg-eval": "stg_train.cli.eval", "stg-synth": "stg_train.cli.synth",
            "stg-convert": "stg_train.cli.convert", "stg-render": "stg_runtime.cli", "stg-view": "stg_runtime.viewer.cli"}
BAD = {"stg-train": ["DATA", "--out", "o", "--iterations", "0"], "stg-eval": ["m.stg"],
       "stg-synth": ["out", "--cameras", "x"], "stg-convert": ["compress", "a.stg"],
       "stg-render": ["m.stg", "--out", "o.mp4", "--size", "x"], "stg-view": ["m.stg", "--port", "x"]}


def seconds(checkout: Path, module: str, argv: list[str]) -> float:
    env = dict(os.environ, PYTHONPATH=str(checkout))
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", module, *argv], cwd=checkout, env=env, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL, check=False)
    return time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeat", type=int, default=7)
    p.add_argument("--against", type=Path, default=None, metavar="CHECKOUT")
    args = p.parse_args()
    checkouts = [ROOT] + ([args.against.resolve()] if args.against else [])
    print(f"{'command':<12} {'case':<8} " + "  ".join(f"{c.name[:18]:>18}" for c in checkouts)
          + ("     ratio" if args.against else ""))
    for prog, module in COMMANDS.items():
        for case, argv in (("--help", ["--help"]), ("bad arg", BAD[prog])):
            times = {c: [] for c in checkouts}
            for _ in range(args.repeat):
                for c in checkouts:  # interleaved, so that a busy moment hits both
                    times[c].append(seconds(c, module, argv))
            medians = [statistics.median(times[c]) for c in checkouts]
            line = f"{prog:<12} {case:<8} " + "  ".join(f"{m:>16.2f} s" for m in medians)
            if args.against:
                line += f"  {medians[1] / medians[0]:>7.1f}x"
            print(line, flush=True)


if __name__ == "__main__":
    main()
