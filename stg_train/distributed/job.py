"""One segment's training run as a job that any worker can run, and run again.

A job is the segment's view of the dataset (segments.segment_view: its frames and context frames, which,
when loaded lazily, are decoded by the job into the segment's own frame-cache chunks), its folder OUT/segments/NN and the settings. A
job always resumes: it continues from the folder's checkpoint.pt when there is one, so a job run again
after its worker died continues from that worker's last checkpoint; the driver removes the checkpoints
of segments that are to be trained afresh before any job starts (make_jobs).
"""
from __future__ import annotations

import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..pipeline import train
from ..segments import segment_dir, segment_view
from ..threads import set_cpu_threads
from ..trainer import TrainConfig, run_steps

#: Seconds between a job's progress reports.
REPORT_INTERVAL = 0.5


@dataclass
class SegmentJob:
    """Segment `index` of the plan: train `dataset` (the segment's view) into `folder` with `config`.
    threads: CPU threads of the worker, torch's and numba's (None: their choice); check: the export check."""

    index: int
    dataset: object
    folder: Path
    config: TrainConfig
    check: bool = True
    threads: int | None = None

    @property
    def steps(self) -> int:
        """The segment's training steps (trainer.run_steps: more than config.iterations with context frames)."""
        return run_steps(self.config.iterations, self.dataset)


def make_jobs(dataset, out: Path, plan, todo, config: TrainConfig, resume: bool, check: bool = True,
              threads: int | None = None) -> list[SegmentJob]:
    """The jobs of segments `todo` of `plan` (stg_train.pipeline.prepare_segments' output). Without
    `resume`, their old checkpoints are removed, so that the jobs start afresh."""
    jobs = []
    for i in todo:
        span, folder = plan[i], segment_dir(out, i, len(plan))
        if not resume:
            (folder / "checkpoint.pt").unlink(missing_ok=True)
        jobs.append(SegmentJob(i, segment_view(dataset, span, config.segment_context), folder, config, check, threads))
    return jobs


def run_segment(job: SegmentJob, report: Callable[..., None], on_step: Callable | None = None) -> int:
    """Run `job` in this process (resuming from its checkpoint when there is one); returns its index.

    report(index, **fields): called with state="running" and host at the start, step=N at most every
    REPORT_INTERVAL seconds, and state="done" at the end. on_step(index, trainer): called after each
    training step (after the checkpoint of that step is written).
    """
    if job.threads:
        set_cpu_threads(job.threads)
    report(job.index, state="running", host=socket.gethostname())
    last = 0.0

    def callback(trainer) -> None:
        nonlocal last
        now = time.monotonic()
        if now - last >= REPORT_INTERVAL or trainer.step == trainer.steps:
            last = now
            report(job.index, step=trainer.step, iterations=trainer.steps)
        if on_step is not None:
            on_step(job.index, trainer)

    job.dataset = job.dataset.chunked(show_progress=False)
    train(job.dataset, job.folder, job.config, resume=True, quiet=True, check=job.check, callback=callback)
    report(job.index, state="done")
    return job.index
