"""`stg-train --gpus`: the segments of a long video in parallel on the GPUs of one machine, no cluster.

One worker process per device (spawned, with CUDA_VISIBLE_DEVICES set to that device before torch
starts CUDA, so each sees its GPU as cuda:0) takes one segment job at a time. DeviceScheduler holds
the scheduling: at most one job per device, the next waiting job to the first free device, a job whose
worker process died run again (resuming from its checkpoint) on a fresh worker of that device. It takes
any executor factory, so it is tested with fake devices and threads; train_on_devices uses processes.
"""
from __future__ import annotations

import multiprocessing
import os
import queue
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Executor, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Callable, Sequence

from ..pipeline import calibrated_once, finish_segments, prepare_segments
from ..trainer import TrainConfig
from . import DistributedError
from .board import Board, Display
from .job import make_jobs, run_segment

POLL_SECONDS = 0.5


def parse_gpus(text: str, count: int, visible: str | None = None) -> list[str]:
    """The CUDA_VISIBLE_DEVICES value of each worker from --gpus: "auto" (every GPU: the entries of
    `visible`, the parent's CUDA_VISIBLE_DEVICES, when set, else 0..count-1) or a list "0,1,3" of
    indices below `count` (of the GPUs this process sees; mapped through `visible`). count: the GPUs
    torch sees. Raises ValueError."""
    ids = [v.strip() for v in visible.split(",") if v.strip()] if visible else [str(i) for i in range(count)]
    ids = ids[:count]
    if text.strip() == "auto":
        if not ids:
            raise ValueError("--gpus auto: no CUDA GPU is visible")
        return ids
    try:
        chosen = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--gpus {text!r}: give auto or GPU indices such as 0,1") from None
    bad = [i for i in chosen if not 0 <= i < len(ids)]
    if not chosen or bad or len(set(chosen)) != len(chosen):
        raise ValueError(f"--gpus {text!r}: this machine has {len(ids)} GPU{'s' if len(ids) != 1 else ''} "
                         f"(indices 0-{len(ids) - 1}); name each once" if ids else f"--gpus {text!r}: no CUDA GPU is visible")
    return [ids[i] for i in chosen]


class DeviceScheduler:
    """Runs jobs on devices, at most one at a time per device.

    new_executor(device): an executor whose work runs on `device` (one worker); a job whose future
    fails with a broken executor (its worker process died) is run again on a fresh executor of the same
    device, up to max_retries times; any other exception cancels the waiting jobs and is raised.
    poll(): called about every poll_seconds while jobs run (the progress display). `log` records
    (event, job index, device) for every start, retry and finish.
    """

    def __init__(self, devices: Sequence[str], new_executor: Callable[[str], Executor], max_retries: int = 3,
                 poll_seconds: float = POLL_SECONDS):
        if not devices:
            raise ValueError("DeviceScheduler: no device")
        self.devices, self.new_executor = list(devices), new_executor
        self.max_retries, self.poll_seconds = max_retries, poll_seconds
        self.log: list[tuple[str, int, str]] = []

    def run(self, jobs: Sequence, work: Callable, poll: Callable[[], None] = lambda: None) -> None:
        """work(job) on the devices' executors for every job (with an `index`)."""
        waiting, running, tries = deque(jobs), {}, {}
        executors = {d: self.new_executor(d) for d in self.devices}
        free = list(self.devices)
        try:
            while waiting or running:
                while waiting and free:
                    device, job = free.pop(0), waiting.popleft()
                    tries[job.index] = tries.get(job.index, 0) + 1
                    self.log.append(("start", job.index, device))
                    running[executors[device].submit(work, job)] = (device, job)
                done, _ = wait(list(running), timeout=self.poll_seconds, return_when=FIRST_COMPLETED)
                poll()
                for future in done:
                    device, job = running.pop(future)
                    try:
                        future.result()
                    except BrokenProcessPool:
                        executors[device].shutdown(wait=False, cancel_futures=True)
                        executors[device] = self.new_executor(device)
                        if tries[job.index] > self.max_retries:
                            raise DistributedError(f"segment {job.index}: its worker process on device {device} "
                                                   f"died on each of {tries[job.index]} tries; run the same "
                                                   "command with --resume to continue from its last checkpoint")
                        self.log.append(("retry", job.index, device))
                        waiting.appendleft(job)
                    else:
                        self.log.append(("done", job.index, device))
                    free.append(device)
        finally:
            for executor in executors.values():
                executor.shutdown(wait=False, cancel_futures=True)
            poll()


# -- the worker processes ---------------------------------------------------------------------------
_REPORTS = None  # the worker's queue of progress reports to the driver


def _start_worker(device: str, reports) -> None:
    """A worker process's initializer: its GPU, its report queue."""
    global _REPORTS
    os.environ["CUDA_VISIBLE_DEVICES"] = device
    _REPORTS = reports


def _work(job, on_step=None) -> int:
    return run_segment(job, lambda index, **fields: _REPORTS.put((index, fields)), on_step)


def process_executors(reports) -> Callable[[str], Executor]:
    """new_executor for DeviceScheduler: a spawned one-process pool per device, reporting to `reports`."""
    context = multiprocessing.get_context("spawn")
    return lambda device: ProcessPoolExecutor(1, mp_context=context, initializer=_start_worker,
                                              initargs=(device, reports))


def train_on_devices(dataset, out, config: TrainConfig, segment_frames: int, devices: Sequence[str],
                     indices: Sequence[int] | None = None, resume: bool = False, quiet: bool = False,
                     check: bool = True, threads: int | None = None, max_retries: int = 3,
                     on_step: Callable | None = None) -> dict:
    """stg_train.pipeline.train_segments with the segments spread over `devices` (CUDA_VISIBLE_DEVICES
    values, parse_gpus), one worker process each; returns its metrics. config.device "cuda" trains on
    each worker's GPU (any other device runs the same scheduling on the CPU). threads: torch threads
    per worker. on_step(index, trainer): run in the worker after each step; it must pickle (a
    module-level function or a functools.partial of one). Raises DistributedError when a segment's
    worker died on every try, DataError and SegmentError as a local run."""
    out = Path(out).resolve()
    dataset, plan, todo = prepare_segments(dataset, out, segment_frames, indices, resume, quiet,
                                                   config.segment_context)
    if todo:
        config, _ = calibrated_once(dataset, config, quiet=quiet)
        jobs = make_jobs(dataset, out, plan, todo, config, resume, check, threads)
        board = Board({j.index: j.steps for j in jobs})
        reports = multiprocessing.get_context("spawn").Queue()
        display = Display(board.snapshot(), enabled=not quiet)

        def poll() -> None:
            while True:
                try:
                    board.update(*reports.get_nowait())
                except queue.Empty:
                    break
            display.show(board.snapshot())

        work = _work if on_step is None else _WorkWith(on_step)
        try:
            DeviceScheduler(devices, process_executors(reports), max_retries).run(jobs, work, poll)
        finally:
            display.close()
    return finish_segments(dataset, out, config, segment_frames, quiet)


class _WorkWith:
    """_work with an on_step hook, picklable for the worker processes."""

    def __init__(self, on_step: Callable):
        self.on_step = on_step

    def __call__(self, job) -> int:
        return _work(job, self.on_step)
