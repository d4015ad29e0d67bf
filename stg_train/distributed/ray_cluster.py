"""`stg-train --ray`: the segments of a long video as Ray tasks on a cluster (the only module that
imports Ray; the `distributed` extra installs it).

train_on_ray connects to the cluster (or starts a local Ray), checks that every node sees DATA and OUT
(stg_train.distributed.storage), runs one task per segment still to train (one GPU each with
config.device "cuda", else `threads` CPUs, default 1), shows one progress display fed by a board actor,
and merges and evaluates the segments into OUT/model.stg as a local run does. A task whose worker dies
(a node lost, a process killed) is retried by Ray up to max_retries times and resumes from the
segment's last checkpoint (stg_train.distributed.job).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Sequence

from stg_runtime.player import RenderError

from ..data import DataError
from ..pipeline import calibrated_once, finish_segments, prepare_segments
from ..segments import SegmentError
from ..trainer import TrainConfig
from . import DistributedError
from .board import Board, Display
from .job import make_jobs, run_segment
from .storage import expectations, node_problems, unshared_message, write_marker

USER_ERRORS = (DataError, SegmentError, RenderError)
INSTALL = 'pip install -e ".[distributed]" (or pip install "ray>=2.9")'
#: Seconds between redraws of the display while tasks run.
POLL_SECONDS = 0.5
#: Seconds the storage check waits for every node.
CHECK_SECONDS = 120


def require_ray():
    """The ray module, or DistributedError saying what to install."""
    try:
        import ray
    except ImportError as e:
        raise DistributedError(f"--ray needs Ray, which is not installed ({e}): {INSTALL}") from None
    return ray


def connect(ray, address: str = "auto") -> bool:
    """Connect to the Ray cluster at `address` ("auto": RAY_ADDRESS, else a cluster started on this
    machine with `ray start`, else a new local Ray); returns whether this call started it (and so
    should shut it down). A Ray already initialised in this process is used as it is."""
    if ray.is_initialized():
        return False
    try:
        ray.init(address=None if address == "auto" else address, log_to_driver=False,
                 logging_level=logging.ERROR, include_dashboard=False)
    except (ConnectionError, ValueError, RuntimeError) as e:
        raise DistributedError(f"--ray {address}: cannot connect to a Ray cluster ({e})") from None
    return True


def check_shared(ray, dataset, out: Path) -> None:
    """DistributedError naming each node that does not see DATA or OUT (storage.node_problems run on
    every live node)."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    marker, token = write_marker(out)
    try:
        expected = expectations(dataset, marker, token)
        probe = ray.remote(num_cpus=0, max_retries=0)(node_problems)
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        names = [f"{n.get('NodeManagerAddress', '?')} ({n['NodeID'][:8]})" for n in nodes]
        refs = [probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False))
                .remote(expected) for n in nodes]
        try:
            found = dict(zip(names, ray.get(refs, timeout=CHECK_SECONDS)))
        except ray.exceptions.GetTimeoutError:
            raise DistributedError(f"the shared-storage check got no answer from every node within "
                                   f"{CHECK_SECONDS} s") from None
        except ray.exceptions.RayError as e:
            raise DistributedError(f"the shared-storage check failed on a node: {e}") from None
        message = unshared_message(found)
        if message:
            raise DistributedError(message)
    finally:
        marker.unlink(missing_ok=True)


def _resources(ray, config: TrainConfig, threads: int | None) -> dict:
    """The task's resources (one GPU with --device cuda; `threads` CPUs, default 1), checked against
    the cluster's largest node."""
    wanted = {"num_cpus": threads or 1}
    if config.device.startswith("cuda"):
        wanted["num_gpus"] = 1
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    for key, name in (("num_cpus", "CPU"), ("num_gpus", "GPU")):
        if key in wanted and not any(r.get(name, 0) >= wanted[key] for r in nodes):
            have = max((r.get(name, 0) for r in nodes), default=0)
            raise DistributedError(f"each segment needs {wanted[key]:g} {name}{'s' if wanted[key] != 1 else ''} "
                                   f"but no node of the Ray cluster has that many (the largest has {have:g})")
    return wanted


def _run_task(job, board, on_step) -> int:
    """A Ray task: run_segment with its reports sent to the board actor."""
    return run_segment(job, lambda index, **fields: board.update.remote(index, fields), on_step)


def _unwrap(ray, error: Exception, job) -> Exception:
    """The exception to raise for a failed task: the task's own DataError, SegmentError or RenderError
    as it is, anything else as a DistributedError naming the segment."""
    cause = getattr(error, "cause", None) if isinstance(error, ray.exceptions.RayTaskError) else None
    if isinstance(cause, USER_ERRORS):
        return cause
    if isinstance(error, ray.exceptions.WorkerCrashedError) or "worker died" in str(error).lower():
        what = "its worker died on every try"
    else:
        what = f"{type(cause or error).__name__}: {str(cause or error).strip().splitlines()[-1]}"
    return DistributedError(f"segment {job.index} ({job.folder}) failed: {what}; run the same command with "
                            "--resume to continue it from its last checkpoint")


def train_on_ray(dataset, out, config: TrainConfig, segment_frames: int, indices: Sequence[int] | None = None,
                 resume: bool = False, quiet: bool = False, check: bool = True, address: str = "auto",
                 threads: int | None = None, max_retries: int = 3,
                 on_step: Callable | None = None) -> dict:
    """stg_train.pipeline.train_segments with the segments as Ray tasks; returns its metrics.

    dataset: best loaded with load_dataset(lazy=True), so that each task decodes only its segment's
    frames. address: the cluster (see connect). threads: CPUs and torch threads per task (default 1).
    max_retries: tries after a task's worker died. on_step(index, trainer): run in the task after each
    step (see job.run_segment). Raises DistributedError (no Ray, no cluster, storage not shared, a task
    out of tries), DataError and SegmentError as a local run.
    """
    ray = require_ray()
    out = Path(out).resolve()
    started = connect(ray, address)
    try:
        dataset, plan, todo = prepare_segments(dataset, out, segment_frames, indices, resume, quiet,
                                               config.segment_context)
        if todo:
            config, _ = calibrated_once(dataset, config, quiet=quiet)
            jobs = make_jobs(dataset, out, plan, todo, config, resume, check, threads)
            resources = _resources(ray, config, threads)
            check_shared(ray, dataset, out)
            _run_jobs(ray, jobs, resources, max_retries, on_step, quiet)
    finally:
        if started:
            ray.shutdown()
    return finish_segments(dataset, out, config, segment_frames, quiet)


def _run_jobs(ray, jobs, resources: dict, max_retries: int, on_step, quiet: bool) -> None:
    """Run the jobs as tasks, drawing the display until all are done; the first failure cancels the
    others and is raised."""
    board = ray.remote(num_cpus=0)(Board).remote({j.index: j.steps for j in jobs})
    task = ray.remote(_run_task).options(max_retries=max_retries, retry_exceptions=False, **resources)
    pending = {task.remote(job, board, on_step): job for job in jobs}
    display = Display(ray.get(board.snapshot.remote()), enabled=not quiet)
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_SECONDS)
            for ref in ready:
                job = pending.pop(ref)
                try:
                    ray.get(ref)
                except Exception as e:  # noqa: BLE001 - every task failure ends the run, named
                    for other in pending:
                        ray.cancel(other, force=True)
                    raise _unwrap(ray, e, job) from None
            display.show(ray.get(board.snapshot.remote()))
    finally:
        display.close()
