"""The one reader of a training checkpoint (OUT/checkpoint.pt, Trainer.save_checkpoint's torch file).

    read_checkpoint(path) -> dict      the state; CheckpointError (a ValueError) naming the file and
                                       the problem for a missing, truncated or foreign file

Trainer.resume, stg_train.pipeline's --resume and stg_train.warm's warm start all read through it, so
a bad checkpoint is an error message, never a traceback.
"""
from __future__ import annotations

import os


class CheckpointError(ValueError):
    """A checkpoint that cannot be read: the message names the file and says why."""


def read_checkpoint(path) -> dict:
    """The state dict saved at `path` (on the CPU; weights_only); CheckpointError if it is unreadable
    or not a dict."""
    import torch

    name = os.fsdecode(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise CheckpointError(f"{name}: no such checkpoint") from None
    except Exception as e:  # torch raises RuntimeError, UnpicklingError, EOFError, ... for bad files
        first = str(e).splitlines()[0] if str(e) else ""
        raise CheckpointError(f"{name}: not a readable checkpoint ({type(e).__name__}: {first})") from None
    if not isinstance(state, dict) or "config" not in state or "params" not in state:
        raise CheckpointError(f"{name}: not a stg-train checkpoint (no config and parameters in it)")
    return state
