"""A simulator of one's own, benchmarked as the GNS is: a per-particle MLP.

Each particle's next acceleration from its own recent velocities and distances to the walls, with no
neighbours at all: a floor under the GNS (what message passing adds, Sec. 3) and a worked example of the
interface in `gns_bench/simulators.py`. It uses the paper's input normalisation and random-walk training
noise (Sec. 4.3) from gns-bench's library, and nothing under `gns_bench/` names it.

Use it without installing anything: with this folder importable (`PYTHONPATH=examples`),

    gns-bench train --config my.toml ...        # my.toml: [model] architecture = "particle_mlp:SPEC"

or register it by entry point in a package of one's own:

    [project.entry-points."gns_bench.simulators"]
    particle_mlp = "particle_mlp:SPEC"
"""

from __future__ import annotations

import torch
from torch import nn

from gns_bench.model.noise import noisy_training_pair
from gns_bench.model.precision import autocast
from gns_bench.model.simulator import kinematic_mask
from gns_bench.simulators import SimulatorSpec


class ParticleMLP(nn.Module):
    """next position = last + last velocity + acceleration(MLP(normalised velocities, clipped wall distances))."""

    uses_edges = False  # rollouts search no neighbours for it
    neighbour_backend = "scipy"
    self_edges = False

    def __init__(self, metadata, input_sequence_length: int, radius: float, noise_std: float, hidden: int = 64):
        super().__init__()
        self.dim = metadata.dim
        self.radius = radius
        self.input_sequence_length = input_sequence_length
        self.register_buffer("bounds", torch.tensor(metadata.bounds, dtype=torch.float32))

        def stats(mean, std):  # the training noise widens the statistics, as the paper's normalisation does
            return (torch.tensor(mean, dtype=torch.float32),
                    torch.sqrt(torch.tensor(std, dtype=torch.float32) ** 2 + noise_std**2))

        for name, (mean, std) in {"velocity": stats(metadata.vel_mean, metadata.vel_std),
                                  "acceleration": stats(metadata.acc_mean, metadata.acc_std)}.items():
            self.register_buffer(f"{name}_mean", mean)
            self.register_buffer(f"{name}_std", std)
        inputs = (input_sequence_length - 1) * self.dim + 2 * self.dim
        self.network = nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                     nn.Linear(hidden, self.dim))

    def build_graph(self, position, batch=None):
        raise NotImplementedError("the per-particle MLP has no graph")

    def forward(self, window: torch.Tensor) -> torch.Tensor:
        """Normalised acceleration [N, D] from a window [N, W, D]."""
        velocities = (window[:, 1:] - window[:, :-1] - self.velocity_mean) / self.velocity_std
        last = window[:, -1]
        walls = torch.cat([last - self.bounds[:, 0], self.bounds[:, 1] - last], dim=1) / self.radius
        return self.network(torch.cat([velocities.flatten(1), walls.clamp(-1.0, 1.0)], dim=1))

    def predict_next_position(self, window, particle_type, batch=None, context=None, edge_index=None, bounds=None,
                              precision: str = "fp32") -> torch.Tensor:
        with autocast(window.device, precision):
            normalised = self(window)
        acceleration = normalised.to(window.dtype) * self.acceleration_std + self.acceleration_mean
        return window[:, -1] + (window[:, -1] - window[:, -2]) + acceleration


def build(config, metadata) -> ParticleMLP:
    return ParticleMLP(metadata, config.model.input_sequence_length, config.model.connectivity_radius,
                       config.train.noise_std)


def loss(simulator: ParticleMLP, batch, position_noise, config, *, model=None, num_moving=None, world_size=1,
         precision="fp32", step=0) -> torch.Tensor:
    """The paper's one-step loss (Sec. 4.3): noisy inputs, the target shifted by the velocity noise, squared error
    of normalised accelerations over the moving particles."""
    window, target = noisy_training_pair(batch.window, batch.target, position_noise, config.train.position_correction)
    acceleration = target - 2.0 * window[:, -1] + window[:, -2]
    wanted = (acceleration - simulator.acceleration_mean) / simulator.acceleration_std
    with autocast(window.device, precision):
        predicted = (model or simulator)(window)
    moving = ~kinematic_mask(batch.particle_type)
    return ((predicted.float() - wanted) ** 2).sum(-1)[moving].mean()


SPEC = SimulatorSpec("particle_mlp", "per-particle MLP", build, loss)
