"""The state of a parallel run's segments and its one progress display.

Workers report (index, fields) updates: state ("waiting", "running", "done"), host, step, iterations.
Every "running" report counts one try, so a job retried after its worker died shows its try number.
The driver folds the updates into a Board and draws one bar: steps done over all segments (a resumed
segment counts from its checkpoint's step), segments done, and each segment's state.
"""
from __future__ import annotations

from stg_runtime.progress import Progress


class Board:
    """Per-segment state of a run. iterations: {index: planned steps} of the segments being trained."""

    def __init__(self, iterations: dict[int, int]):
        self.segments = {i: {"state": "waiting", "step": 0, "iterations": n, "tries": 0, "host": ""}
                         for i, n in sorted(iterations.items())}

    def update(self, index: int, fields: dict) -> None:
        seg = self.segments[index]
        if fields.get("state") == "running":
            seg["tries"] += 1
        seg.update(fields)
        if seg["state"] == "done":
            seg["step"] = seg["iterations"]

    def snapshot(self) -> dict:
        return {i: dict(s) for i, s in self.segments.items()}


def steps_done(snapshot: dict) -> int:
    return sum(s["step"] for s in snapshot.values())


def describe(snapshot: dict, width: int = 2) -> dict:
    """The display's figures: segments done of all, then one entry per segment (waiting, host and
    step/iterations while running, with the try number after a retry, done)."""
    done = sum(s["state"] == "done" for s in snapshot.values())
    figures = {"done": f"{done}/{len(snapshot)}"}
    for i, s in snapshot.items():
        if s["state"] == "running":
            text = f"{s['step']}/{s['iterations']}" + (f"@{s['host']}" if s["host"] else "")
            text += f" (try {s['tries']})" if s["tries"] > 1 else ""
        else:
            text = s["state"]
        figures[f"{i:0{width}d}"] = text
    return figures


class Display:
    """One progress bar for the whole run (stderr; nothing when not enabled)."""

    def __init__(self, snapshot: dict, enabled: bool = True):
        self.bar = Progress(total=sum(s["iterations"] for s in snapshot.values()), desc="segments", enabled=enabled)
        self.width = max(2, len(str(max(snapshot, default=0))))
        self.show(snapshot)

    def show(self, snapshot: dict) -> None:
        """Redraw when a step or a state changed."""
        figures, steps = describe(snapshot, self.width), steps_done(snapshot)
        if figures != self.bar.figures or steps != self.bar.count:
            self.bar.figures = figures
            self.bar.update(steps - self.bar.count)

    def close(self) -> None:
        self.bar.close()
