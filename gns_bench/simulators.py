"""Simulators by name: what `model.architecture` selects, for training, evaluation, rollouts, stress tests and
reports alike.

A simulator is an `nn.Module` that predicts next positions from a window of positions (the GNS, Sec. 3; the
baselines of Sec. 5.5); its `SimulatorSpec` says how to build it for a dataset, its training loss, its learning
rate schedule and its optimiser's settings. The paper's GNS, CConv and DPI-Net register here. A model of
one's own registers

- by entry point: `[project.entry-points."gns_bench.simulators"] my_model = "my_package.module:SPEC"`, then
  `model.architecture = "my_model"`;
- or by path: `model.architecture = "my_package.module:SPEC"` (a module importable from where gns-bench runs);
- or in code: `register(SimulatorSpec(...))`.

What the module must offer evaluation and rollouts: `dim`, `radius`, `bounds` (tensor [D, 2]),
`input_sequence_length`, `uses_edges` (False: rollouts search no neighbours for it), `neighbour_backend` and
`self_edges` (read only when `uses_edges`), `build_graph(position, batch)` (likewise), and
`predict_next_position(window [N, W, D], particle_type [N], batch [N] or None, context [B, C] or None,
edge_index or None, bounds or None, precision)` -> [N, D]. `examples/particle_mlp.py` is a complete one.
Optional: `predicts_moving_only = True` says its `predict_next_position` also takes `moving_only=True`, and
then may skip kinematic particles' work (rollouts overwrite their positions with the data; `eval.moving_only`);
`caches_static_encodings = True`, that it takes `static_encodings=StaticEncodings(static)` and reuses the encoder's
latents of never-moving particles across a rollout's steps (`eval.static_encodings`).

This module sits above `model/` and `train/` (it names what both hold) and imports them only when a simulator
is built or trained.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any

from gns_bench.config import ConfigError

if TYPE_CHECKING:
    import torch

    from gns_bench.config import Config
    from gns_bench.data.format import Metadata

ENTRY_POINT_GROUP = "gns_bench.simulators"
Loss = Callable[..., "torch.Tensor"]


def paper_schedule(config: Config) -> Callable[[int], float]:
    """The paper's learning rate: exponential decay from `train.learning_rate` towards `train.learning_rate_final`,
    10x every `train.learning_rate_decay_steps` (App. B.3; `train.losses.learning_rate`)."""
    from gns_bench.train.losses import learning_rate

    return lambda step: learning_rate(step, config.train)


@dataclass(frozen=True)
class SimulatorSpec:
    """How gns-bench builds, trains and names one kind of simulator.

    build(config, metadata): a fresh module for that dataset (the config already resolved against it).
    loss(simulator, batch, position_noise, config, *, model, num_moving, world_size, precision, step): the
      training loss on a `GraphBatch` at training step `step` (`position_noise`: the random-walk noise drawn for
      it, Sec. 4.3).
    schedule(config): the learning rate by step. adam_eps(config): Adam's epsilon.
    unrolled_steps(config): frames after each training window the loss needs (1: one-step training).
    data_parallel: whether torchrun's data parallelism may train it (its loss scales by `world_size`)."""

    name: str
    display_name: str
    build: Callable[[Config, Metadata], Any]
    loss: Loss
    schedule: Callable[[Config], Callable[[int], float]] = paper_schedule
    adam_eps: Callable[[Config], float] = lambda config: 1e-8
    unrolled_steps: Callable[[Config], int] = lambda config: 1
    data_parallel: bool = False


_REGISTRY: dict[str, SimulatorSpec] = {}


def register(spec: SimulatorSpec) -> SimulatorSpec:
    """Make `spec` available as `model.architecture = spec.name` (a name taken already is refused)."""
    if spec.name in _REGISTRY and _REGISTRY[spec.name] is not spec:
        raise ValueError(f"a simulator named {spec.name!r} is registered already")
    _REGISTRY[spec.name] = spec
    return spec


def _from_path(path: str) -> SimulatorSpec:
    module_name, _, attribute = path.partition(":")
    try:
        found = getattr(importlib.import_module(module_name), attribute)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"model.architecture = {path!r}: cannot import {attribute!r} from {module_name!r} "
                         f"({exc})") from None
    if not isinstance(found, SimulatorSpec):
        raise ValueError(f"model.architecture = {path!r}: expected a gns_bench.model.registry.SimulatorSpec, got "
                         f"{type(found).__name__}")
    return found


def get(name: str) -> SimulatorSpec:
    """The spec `model.architecture = name` selects: registered here, by an installed package's entry point,
    or `module:attribute`."""
    if name in _REGISTRY:
        return _REGISTRY[name]
    if ":" in name:
        spec = _from_path(name)
        _REGISTRY[name] = spec
        return spec
    for point in entry_points(group=ENTRY_POINT_GROUP):
        if point.name == name:
            spec = point.load()
            if not isinstance(spec, SimulatorSpec):
                raise ValueError(f"entry point {ENTRY_POINT_GROUP}:{name} ({point.value}) is not a SimulatorSpec")
            return register(spec)
    known = sorted({*_REGISTRY, *(p.name for p in entry_points(group=ENTRY_POINT_GROUP))})
    raise ValueError(f"model.architecture = {name!r}: no such simulator; registered: {', '.join(known)} (or give "
                     "'package.module:SPEC')")


def display_names() -> dict[str, str]:
    """name -> display name of every simulator registered so far (the built-in ones first)."""
    return {name: spec.display_name for name, spec in _REGISTRY.items()}


def display_name(name: str) -> str:
    """How reports name the simulator (the papers' names for the built-in ones)."""
    try:
        return get(name).display_name
    except ValueError:
        return name


def build(config: Config, metadata: Metadata) -> Any:
    """A fresh simulator of `config.model.architecture` for `metadata`'s dataset, told its registered name (its
    `architecture` attribute, which reports and checkpoints read)."""
    spec = get(config.model.architecture)
    simulator = spec.build(config, metadata)
    simulator.architecture = spec.name if ":" not in config.model.architecture else config.model.architecture
    return simulator


# ---------------------------------------------------------------------------------------------------------
# The paper's GNS and the baselines it is compared with (Sec. 5.5, App. D), built lazily
# ---------------------------------------------------------------------------------------------------------

def _build_gns(config: Config, metadata: Metadata):
    from gns_bench.model.simulator import LearnedSimulator

    return LearnedSimulator(config.model, metadata, config.train.noise_std)


def _gns_loss(simulator, batch, position_noise, config, *, model=None, num_moving=None, world_size=1,
              precision="fp32", step=0):
    from gns_bench.train.losses import pushforward_unroll, training_loss

    return training_loss(simulator, batch, position_noise, config.train.position_correction, model, num_moving,
                         world_size, precision, pushforward_unroll(config.train, step), config.train.moving_only)


def _radius(config: Config) -> float:
    """The connectivity radius the baselines start from: `model.connectivity_radius`, resolved against the
    dataset where it was opened (`config.resolve_for_dataset`)."""
    if config.model.connectivity_radius is None:
        raise ConfigError("model.connectivity_radius is unset: resolve the config against the dataset first "
                          "(config.resolve_for_dataset)")
    return float(config.model.connectivity_radius)


def _build_cconv(config: Config, metadata: Metadata):
    from gns_bench.model.cconv import CConvSimulator

    return CConvSimulator(config.cconv, metadata, _radius(config),
                          input_sequence_length=config.model.input_sequence_length, wall_range=config.model.wall_range)


def _cconv_loss(simulator, batch, position_noise, config, *, model=None, num_moving=None, world_size=1,
                precision="fp32", step=0):
    """CConv's authors' unrolled loss (they train without noise: train.noise_std = 0 in its sweeps)."""
    import torch

    future = batch.future if batch.future is not None else batch.target[:, None]
    window = torch.cat([batch.window, future], 1)
    return simulator.unrolled_loss(window, batch.particle_type, batch.batch, batch.context, precision=precision,
                                   position_noise=position_noise, position_correction=config.train.position_correction)


def _cconv_schedule(config: Config) -> Callable[[int], float]:
    """CConv's authors' piecewise schedule over the run (`cconv.*`)."""
    from gns_bench.model.cconv import learning_rate

    return lambda step: learning_rate(config.cconv, step, config.train.steps)


def _build_dpi(config: Config, metadata: Metadata):
    from gns_bench.model.dpi import DPISimulator

    return DPISimulator(config.dpi, metadata, _radius(config),
                        input_sequence_length=config.model.input_sequence_length)


def _dpi_loss(simulator, batch, position_noise, config, *, model=None, num_moving=None, world_size=1,
              precision="fp32", step=0):
    """DPI-Net's loss on normalised next velocities; noise as the GNS's (their recipe: train.noise_std = 0)."""
    return simulator.training_loss(batch.window, batch.target, batch.particle_type, batch.batch, position_noise,
                                   precision=precision)


GNS = register(SimulatorSpec("gns", "GNS", _build_gns, _gns_loss, data_parallel=True,
                             unrolled_steps=lambda config: 1 + config.train.pushforward_steps))
CCONV = register(SimulatorSpec("cconv", "CConv", _build_cconv, _cconv_loss, schedule=_cconv_schedule,
                               adam_eps=lambda config: config.cconv.adam_eps,
                               unrolled_steps=lambda config: config.cconv.unrolled_steps))
DPI = register(SimulatorSpec("dpi", "DPI-Net", _build_dpi, _dpi_loss))
