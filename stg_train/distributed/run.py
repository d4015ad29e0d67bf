"""The one call behind `stg-train --ray` and `stg-train --gpus`: which parallel runner, with what."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

from ..trainer import TrainConfig
from . import DistributedError


def train_parallel(dataset, out: Path, config: TrainConfig, segment_frames: int, segments: Sequence[int] | None = None,
                   resume: bool = False, quiet: bool = False, check: bool = True, ray: str | None = None,
                   gpus: str | None = None, threads: int | None = None) -> dict:
    """Train the segments on the Ray cluster `ray` (an address or "auto": ray_cluster.train_on_ray) or
    on the local GPUs `gpus` ("auto" or "0,1,...": local.train_on_devices); returns the metrics of
    stg_train.pipeline.train_segments. Raises DistributedError for a bad --gpus or anything the runners
    raise."""
    if ray is not None:
        from .ray_cluster import train_on_ray

        return train_on_ray(dataset, out, config, segment_frames, segments, resume, quiet, check, address=ray,
                            threads=threads)
    import torch

    from .local import parse_gpus, train_on_devices

    try:
        devices = parse_gpus(gpus, torch.cuda.device_count(), os.environ.get("CUDA_VISIBLE_DEVICES"))
    except ValueError as e:
        raise DistributedError(str(e)) from None
    return train_on_devices(dataset, out, config, segment_frames, devices, segments, resume, quiet, check, threads)
