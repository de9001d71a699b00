"""An exponential moving average of the weights (Polyak averaging), the model a run with `train.weight_average`
is evaluated with. Not in the paper, whose rate decays to 1e-6 over 20M steps so that its last weights are
already an average of sorts; at the constant rate of a learning curve (App. B.3's schedule at its peak) the
weights wander about their minimum from step to step, and a snapshot's error with them.

The average starts at the weights it is first given and moves towards each step's weights by
1 - min(decay, (1 + n) / (10 + n)) after its n-th update: the short memory of the first updates keeps
a fresh run's average from remembering its random initial weights (TensorFlow's ExponentialMovingAverage
with `num_updates`).
"""

from __future__ import annotations

from typing import Any

import torch


def averaged(model_state: dict[str, torch.Tensor], average: dict[str, Any] | None) -> dict[str, torch.Tensor]:
    """A model's state dict with each parameter the average holds (`WeightAverage.state_dict()`, as a checkpoint
    keeps it) replaced by its average, in the parameter's dtype; `model_state` itself without one."""
    if average is None:
        return model_state
    unknown = set(average["values"]) - set(model_state)
    if unknown:
        raise ValueError(f"weight average: averaged parameters {sorted(unknown)[:3]} are not the model's")
    return {name: (average["values"][name].to(value.device, value.dtype) if name in average["values"] else value)
            for name, value in model_state.items()}


def effective_decay(decay: float, updates: int) -> float:
    """The decay of the average's update after `updates` earlier ones: `decay`, shortened while few."""
    return min(decay, (1.0 + updates) / (10.0 + updates))


class WeightAverage:
    """The average of `module`'s floating-point parameters, in float32 whatever the parameters' type; buffers
    (the normalisation statistics) are the module's own and are not averaged. It follows the parameter tensors
    themselves, which training updates in place (a compiled or data-parallel wrapper shares them)."""

    def __init__(self, module: torch.nn.Module, decay: float):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"weight average decay {decay}: expected 0 < decay < 1")
        self.decay = decay
        self.updates = 0
        named = [(name, p) for name, p in module.named_parameters() if p.dtype.is_floating_point]
        self.names = [name for name, _ in named]
        self._live = [p.detach() for _, p in named]
        self.values = [p.to(torch.float32).clone() for p in self._live]

    def update(self) -> None:
        """Move the average towards the parameters as they are now (after an optimiser step)."""
        weight = 1.0 - effective_decay(self.decay, self.updates)
        torch._foreach_lerp_(self.values, [p.to(torch.float32) for p in self._live], weight)
        self.updates += 1

    def state_dict(self) -> dict[str, Any]:
        return {"decay": self.decay, "updates": self.updates, "values": dict(zip(self.names, self.values,
                                                                                     strict=True))}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Resume the average a checkpoint holds; its parameters must be this module's."""
        values = state["values"]
        if set(values) != set(self.names):
            raise ValueError("weight average: the checkpoint's averaged parameters are not this model's")
        self.updates = int(state["updates"])
        self.values = [values[name].to(self.values[i].device, torch.float32).clone()
                       for i, name in enumerate(self.names)]
