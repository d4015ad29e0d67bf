"""Segments in parallel (stg_train.distributed): a local Ray (started here with 2 CPUs) trains a
two-segment synthetic scene into the same model as a sequential run; a worker killed inside a segment
is retried and resumes from the segment's checkpoint; storage that a node does not see, a missing DATA
and a missing Ray give one clear error; each segment decodes only its own frames into its own cache;
the local multi-GPU scheduler, on fake devices (threads, then CPU worker processes)."""
from __future__ import annotations

import functools
import os
import signal
import sys
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")
ray = pytest.importorskip("ray")

from stg_runtime import format as stg_format  # noqa: E402
from stg_train.cli.train import main as train_main  # noqa: E402
from stg_train.data import load_dataset  # noqa: E402
from stg_train.distributed import DistributedError  # noqa: E402
from stg_train.distributed import ray_cluster  # noqa: E402
from stg_train.distributed.local import DeviceScheduler, parse_gpus, train_on_devices  # noqa: E402
from stg_train.distributed.ray_cluster import train_on_ray  # noqa: E402
from stg_train.trainer import TrainConfig  # noqa: E402

SCENE = dict(num_cameras=4, num_frames=8, fps=4.0, width=64, height=48)
ARGS = ["--segment-frames", "4", "--iterations", "10", "--points", "200", "--init", "volume",
        "--checkpoint-every", "5", "--quiet", "--threads", "1"]
CONFIG = dict(iterations=10, num_points=200, init="volume", checkpoint_every=5)


@pytest.fixture(scope="module")
def scene_dir(synthetic_n3v):
    return synthetic_n3v("dist_scene", **SCENE)


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray of 2 CPUs for this module (shut down after it)."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def sequential(scene_dir, tmp_path_factory):
    """Both segments trained one after the other in this process, 1 torch thread: OUT."""
    out = tmp_path_factory.mktemp("dist_runs") / "sequential"
    threads = torch.get_num_threads()
    try:
        assert train_main([str(scene_dir), "--out", str(out)] + ARGS) == 0
    finally:
        torch.set_num_threads(threads)
    return out


def _assert_same_model(a_path, b_path) -> None:
    a, b = stg_format.load(a_path), stg_format.load(b_path)
    assert len(a.segments) == len(b.segments) == 2
    for sa, sb in zip(a.segments, b.segments):
        assert (sa.start_frame, sa.num_frames, sa.decoder) == (sb.start_frame, sb.num_frames, sb.decoder)
        for name, arr in sa.arrays().items():
            np.testing.assert_array_equal(arr, getattr(sb, name), err_msg=name)


def _config() -> TrainConfig:
    return TrainConfig(**CONFIG)


# -- Ray -------------------------------------------------------------------------------------------
def test_ray_run_equals_the_sequential_run(local_ray, scene_dir, sequential, tmp_path, capsys):
    out = tmp_path / "ray"
    assert train_main([str(scene_dir), "--out", str(out), "--ray"] + ARGS) == 0
    _assert_same_model(out / "model.stg", sequential / "model.stg")
    for k in (0, 1):
        assert {"checkpoint.pt", "model.stg", "metrics.json"} <= {p.name for p in (out / "segments" / f"0{k}").iterdir()}
    assert "PSNR" in capsys.readouterr().out
    # the frame cache: one file per segment, none of the whole video
    cache = scene_dir / ".stg_cache" / "n3v_images_x1_f8"
    assert (cache / "frames_0-3" / "frames_uint8.npy").exists() and (cache / "frames_4-7" / "frames_uint8.npy").exists()
    assert not (cache / "frames_uint8.npy").exists()
    assert not list((out / "segments").glob(".shared-storage-*"))  # the check's marker is removed


def test_killed_worker_resumes_from_its_checkpoint(local_ray, scene_dir, sequential, tmp_path):
    out, log = tmp_path / "killed", tmp_path / "steps.log"

    def kill_once_in_segment_1(index, trainer):  # runs in the Ray worker (pickled by value)
        with open(log, "a") as f:
            f.write(f"{index} {os.getpid()} {trainer.step}\n")
        if index == 1 and trainer.step == 7 and not (log.parent / "worker-killed").exists():
            (log.parent / "worker-killed").write_text("")
            os.kill(os.getpid(), signal.SIGKILL)  # two steps after the checkpoint at step 5

    dataset = load_dataset(scene_dir, lazy=True)
    metrics = train_on_ray(dataset, out, _config(), 4, quiet=True, threads=1, on_step=kill_once_in_segment_1)
    assert metrics["missing_segments"] == []
    rows = [tuple(map(int, line.split())) for line in log.read_text().splitlines()]
    tries = {}
    for index, pid, step in rows:
        if index == 1:
            tries.setdefault(pid, []).append(step)
    # killed at 7, resumed at 6; 20 steps: 10 x 8 frames (4 and 4 of context, the default) / 4 shown
    assert list(tries.values()) == [list(range(1, 8)), list(range(6, 21))]
    _assert_same_model(out / "model.stg", sequential / "model.stg")


def test_unshared_storage_is_named(local_ray, scene_dir, tmp_path, monkeypatch, capsys):
    real = ray_cluster.expectations

    def as_a_node_with_its_own_disks_sees_it(dataset, marker, token):
        expected = real(dataset, marker, token)
        expected["files"][0][1] += 1                             # another file at DATA's path
        expected["marker"][0] = str(tmp_path / "elsewhere" / "segments" / Path(marker).name)  # another OUT
        return expected

    monkeypatch.setattr(ray_cluster, "expectations", as_a_node_with_its_own_disks_sees_it)
    out = tmp_path / "out"
    assert train_main([str(scene_dir), "--out", str(out), "--ray"] + ARGS) == 2
    err = capsys.readouterr().err
    assert "stg-train: error: DATA and OUT must be on storage that every node" in err and "Traceback" not in err
    assert "DATA file" in err and "cam00" in err and "bytes here" in err
    assert "the driver's marker" in err and "cannot be read" in err
    assert not (out / "segments" / "00" / "checkpoint.pt").exists()  # nothing trained


def test_missing_paths_and_missing_ray(local_ray, scene_dir, tmp_path, monkeypatch, capsys):
    assert train_main([str(tmp_path / "nowhere"), "--out", str(tmp_path / "o"), "--ray"] + ARGS) == 2
    assert "nowhere: no such directory" in capsys.readouterr().err
    (tmp_path / "file").write_text("")
    assert train_main([str(scene_dir), "--out", str(tmp_path / "file" / "out"), "--ray"] + ARGS) == 2
    assert "out: cannot create it" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "ray", None)  # as without the distributed extra
    assert train_main([str(scene_dir), "--out", str(tmp_path / "o"), "--ray"] + ARGS) == 2
    err = capsys.readouterr().err
    assert "--ray needs Ray" in err and 'pip install -e ".[distributed]"' in err and "Traceback" not in err
    assert train_main([str(scene_dir), "--out", str(tmp_path / "o"), "--gpus", "0"] + ARGS) == 2
    assert "add --device cuda" in capsys.readouterr().err


# -- the local GPU scheduler, on fake devices --------------------------------------------------------
def test_parse_gpus():
    assert parse_gpus("auto", 2) == ["0", "1"]
    assert parse_gpus("auto", 2, visible="3,5") == ["3", "5"] and parse_gpus("1", 2, visible="3,5") == ["5"]
    assert parse_gpus("1,0", 4) == ["1", "0"]
    for text, count, message in (("2", 2, "indices 0-1"), ("0,0", 2, "once"), ("x", 2, "auto or GPU"),
                                 ("auto", 0, "no CUDA GPU"), ("0", 0, "no CUDA GPU")):
        with pytest.raises(ValueError, match=message):
            parse_gpus(text, count)


class _FakeDevices:
    """Executors of one thread per fake device that record which jobs run where and when; a job in
    `die` fails as if its worker process had died, on its first `times` tries."""

    def __init__(self, die=(), times=1):
        self.lock, self.running, self.intervals, self.created = threading.Lock(), {}, [], []
        self.die, self.times, self.deaths = set(die), times, {}

    def new_executor(self, device):
        self.created.append(device)
        pool = ThreadPoolExecutor(1)
        outer = self

        class Executor:
            def submit(self, work, job) -> Future:
                return pool.submit(outer.run, device, work, job)

            def shutdown(self, wait=True, cancel_futures=False):
                pool.shutdown(wait=wait, cancel_futures=cancel_futures)
        return Executor()

    def run(self, device, work, job):
        with self.lock:
            assert device not in self.running, f"two jobs at once on {device}"
            self.running[device] = job.index
        start = time.monotonic()
        try:
            if job.index in self.die and self.deaths.get(job.index, 0) < self.times:
                self.deaths[job.index] = self.deaths.get(job.index, 0) + 1
                raise BrokenProcessPool("worker died")
            return work(job)
        finally:
            with self.lock:
                del self.running[device]
                self.intervals.append((device, job.index, start, time.monotonic()))


def _jobs(n):
    return [SimpleNamespace(index=i) for i in range(n)]


def test_scheduler_runs_each_job_once_one_per_device_in_parallel():
    fake = _FakeDevices()
    polls = []
    scheduler = DeviceScheduler(["gpu-a", "gpu-b"], fake.new_executor, poll_seconds=0.01)
    scheduler.run(_jobs(5), lambda job: time.sleep(0.05), poll=lambda: polls.append(1))
    assert sorted(i for _, i, _, _ in fake.intervals) == [0, 1, 2, 3, 4]
    assert {d for d, _, _, _ in fake.intervals} == {"gpu-a", "gpu-b"}
    (_, _, s0, e0), (_, _, s1, e1) = sorted([iv for iv in fake.intervals if iv[1] in (0, 1)], key=lambda iv: iv[1])
    assert s1 < e0 and s0 < e1  # the first two jobs ran at the same time, on the two devices
    assert [e for e, _, _ in scheduler.log].count("start") == 5 and polls


def test_scheduler_retries_a_dead_worker_on_a_fresh_executor_then_gives_up():
    fake = _FakeDevices(die={2}, times=1)
    scheduler = DeviceScheduler(["gpu-a", "gpu-b"], fake.new_executor, poll_seconds=0.01)
    scheduler.run(_jobs(4), lambda job: time.sleep(0.01))
    assert [e for e, i, _ in scheduler.log if i == 2] == ["start", "retry", "start", "done"]
    assert sorted(i for e, i, _ in scheduler.log if e == "done") == [0, 1, 2, 3] and len(fake.created) == 3
    fake = _FakeDevices(die={1}, times=10)
    with pytest.raises(DistributedError, match="segment 1: its worker process on device .* died on each of 3 tries"):
        DeviceScheduler(["gpu-a"], fake.new_executor, max_retries=2, poll_seconds=0.01).run(_jobs(3), lambda j: None)


def test_scheduler_raises_a_job_error():
    def work(job):
        if job.index == 1:
            raise ValueError("bad segment")
    with pytest.raises(ValueError, match="bad segment"):
        DeviceScheduler(["a", "b"], _FakeDevices().new_executor, poll_seconds=0.01).run(_jobs(3), work)


def _record_device(log: Path, index: int, trainer) -> None:
    """on_step of the worker processes (module level: it is pickled into them)."""
    with open(log, "a") as f:
        f.write(f"{index} {os.environ.get('CUDA_VISIBLE_DEVICES')} {os.getpid()}\n")


def test_worker_processes_on_fake_devices_equal_the_sequential_run(scene_dir, sequential, tmp_path):
    log = tmp_path / "devices.log"
    dataset = load_dataset(scene_dir, lazy=True)
    train_on_devices(dataset, tmp_path / "local", _config(), 4, ["fake0", "fake1"], quiet=True, threads=1,
                     on_step=functools.partial(_record_device, log))
    rows = {tuple(line.split()) for line in log.read_text().splitlines()}
    assert {(i, d) for i, d, _ in rows} in ({("0", "fake0"), ("1", "fake1")}, {("0", "fake1"), ("1", "fake0")})
    assert len({pid for _, _, pid in rows}) == 2 and str(os.getpid()) not in {pid for _, _, pid in rows}
    _assert_same_model(tmp_path / "local" / "model.stg", sequential / "model.stg")
