"""Editing the Gaussians with the optimizer in step: every raw parameter tensor and its Adam moments
change together, so that Adam continues as if the edited Gaussians had always been there (appended
ones start with zero moments)."""
from __future__ import annotations

import torch
from torch import Tensor

from ..params import STGParams


def _swap(params: STGParams, optimizer: torch.optim.Optimizer, name: str, new_value: Tensor, edit_state) -> None:
    """Replace raw parameter `name` by new_value (a fresh leaf), editing its Adam moments with edit_state."""
    old = params.raw[name]
    new = new_value.detach().contiguous().requires_grad_(old.requires_grad)
    params.raw[name] = new
    for group in optimizer.param_groups:
        if group.get("name") == name:
            group["params"][0] = new
            state = optimizer.state.pop(old, None)
            if state:
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in state:
                        state[key] = edit_state(state[key])
                optimizer.state[new] = state
            return


def append_gaussians(params: STGParams, optimizer: torch.optim.Optimizer, new: dict[str, Tensor]) -> None:
    """Add Gaussians at the end: new[name] (K, ...) raw values for every name in params.raw; their Adam
    moments start at zero."""
    k = next(iter(new.values())).shape[0]
    for name, value in params.raw.items():
        extra = new[name].to(value)
        _swap(params, optimizer, name, torch.cat([value.detach(), extra]),
              lambda s, k=k: torch.cat([s, s.new_zeros((k,) + s.shape[1:])]))


def keep_gaussians(params: STGParams, optimizer: torch.optim.Optimizer, keep: Tensor) -> None:
    """Keep only the Gaussians where keep (N,) bool is True (values and Adam moments)."""
    for name, value in params.raw.items():
        _swap(params, optimizer, name, value.detach()[keep], lambda s: s[keep])


def set_values(params: STGParams, optimizer: torch.optim.Optimizer, name: str, value: Tensor) -> None:
    """Overwrite raw parameter `name` and zero its Adam moments (as 3DGS's opacity reset does)."""
    _swap(params, optimizer, name, value, torch.zeros_like)
