"""Exponential moving average of a model's weights (for validation and shipping).

After every optimiser step t = 0, 1, 2, …: θ_ema ← β_t·θ_ema + (1 − β_t)·θ with β_t = min(β, (1 + t)/(10 + t))
(the warm-up of TensorFlow's ``ExponentialMovingAverage(num_updates=t)``, so a short run is not dominated by the
initial weights). Floating-point buffers are averaged like parameters; integer buffers are copied.
"""

from __future__ import annotations

import copy

import torch
from torch import nn


class EMA:
    """An averaged copy of ``model`` (same class, config and device), updated with :meth:`update`.

    Args:
        model: the model being trained (its current weights start the average).
        decay: β, e.g. 0.999.
    """

    def __init__(self, model: nn.Module, decay: float):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"EMA decay must be in (0, 1), got {decay}")
        self.decay = float(decay)
        self.model = copy.deepcopy(model).eval().requires_grad_(False)
        self.updates = 0

    def decay_at(self, t: int) -> float:
        """β_t = min(β, (1 + t) / (10 + t))."""
        return min(self.decay, (1.0 + t) / (10.0 + t))

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """One averaging step towards ``model``'s current weights."""
        beta = self.decay_at(self.updates)
        avg, cur = [], []
        for e, p in zip(self.model.state_dict().values(), model.state_dict().values()):
            if e.is_floating_point():
                avg.append(e)
                cur.append(p.detach())
            else:
                e.copy_(p)
        if avg:
            torch._foreach_lerp_(avg, cur, 1.0 - beta)  # e + (1 − β)(p − e) = β·e + (1 − β)·p
        self.updates += 1

    def state_dict(self) -> dict:
        return {"model": self.model.state_dict(), "updates": torch.tensor(self.updates)}

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        self.updates = int(state["updates"])
