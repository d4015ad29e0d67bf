"""A small progress bar on stderr (redrawn in place on a terminal, a line every few seconds otherwise)."""
from __future__ import annotations

import sys
import time
from contextlib import contextmanager


class Progress:
    """Usage: `for x in Progress(items, desc="render"): ...`, or `bar = Progress(total=n)` with
    `bar.update(k)`, `bar.set(loss=0.1)` for figures shown after the bar, and `bar.close()`."""

    def __init__(self, iterable=None, total: int | None = None, desc: str = "", enabled: bool = True,
                 stream=None, interval: float | None = None):
        self.iterable = iterable
        self.total = total if total is not None else (len(iterable) if hasattr(iterable, "__len__") else None)
        self.desc, self.enabled = desc, enabled
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.interval = interval if interval is not None else (0.1 if self.tty else 5.0)
        self.count, self.figures, self._drawn = 0, {}, -1
        self.start = self._last = time.perf_counter()

    def __iter__(self):
        try:
            for item in self.iterable:
                yield item
                self.update()
        finally:
            self.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def set(self, **figures) -> None:
        self.figures.update(figures)

    def update(self, n: int = 1) -> None:
        self.count += n
        now = time.perf_counter()
        if now - self._last >= self.interval or self.count == self.total:
            self._last = now
            self._draw(final=False)

    def close(self) -> None:
        if self.enabled and self.start is not None and (self.tty or self._drawn != self.count):
            self._draw(final=True)
        self.start = None

    def _draw(self, final: bool) -> None:
        if not self.enabled or self.start is None:
            return
        elapsed = time.perf_counter() - self.start
        rate = self.count / elapsed if elapsed > 0 else 0.0
        if self.total:
            frac = min(1.0, self.count / self.total)
            bar = "#" * int(24 * frac) + "-" * (24 - int(24 * frac))
            eta = (self.total - self.count) / rate if rate > 0 else 0.0
            head = f"{self.desc} [{bar}] {self.count}/{self.total} {rate:.2f}/s eta {eta:.0f}s"
        else:
            head = f"{self.desc} {self.count} {rate:.2f}/s"
        tail = " ".join(f"{k}={_fmt(v)}" for k, v in self.figures.items())
        line = f"{head} {tail}".rstrip()
        self._drawn = self.count
        if self.tty:
            self.stream.write("\r" + line + "\033[K" + ("\n" if final else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


@contextmanager
def progress_callback(desc: str, enabled: bool = True):
    """`with progress_callback("decode frames") as report: work(progress=report)`: a report(done, total)
    callback for work that reports its own progress. The bar opens at the first report (nothing is drawn
    when none comes, e.g. when the work was cached) and closes when the block ends: progress_stages
    with one stage."""
    with progress_stages(enabled) as stage:
        yield stage(desc)


def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


@contextmanager
def progress_stages(enabled: bool = True):
    """`with progress_stages() as stage: work(a=stage("first"), b=stage("second"))`: report(done, total)
    callbacks for pieces of work done one after the other, a bar each. A stage's bar opens at its first
    report (nothing is drawn for a stage that reports nothing) and closes when another stage reports
    or the block ends."""
    current = [None, None]  # desc, bar

    def stage(desc: str):
        def report(done: int, total: int) -> None:
            if current[0] != desc:
                if current[1] is not None:
                    current[1].close()
                current[:] = [desc, Progress(total=total, desc=desc, enabled=enabled)]
            current[1].update(done - current[1].count)
        return report

    try:
        yield stage
    finally:
        if current[1] is not None:
            current[1].close()
