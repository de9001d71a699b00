"""The learned simulator: features in, normalised acceleration out, semi-implicit Euler to positions.

This is the paper's GNS (Sec. 3, App. A/B.2; details as in DeepMind's released code,
learning_to_simulate/learned_simulator.py). It holds the dataset's normalisation statistics as buffers,
so a checkpoint carries everything needed to run it.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from gns_bench.config import ConfigError, ModelConfig
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, NUM_PARTICLE_TYPES, Metadata
from gns_bench.model import features
from gns_bench.model.neighbours import radius_graph
from gns_bench.model.network import EncodeProcessDecode, sonnet_init_
from gns_bench.model.precision import autocast
from gns_bench.model.static_encodings import StaticEncodings

CONTEXT_STD_FLOOR = 1e-8


class GraphInputs(NamedTuple):
    """What the encoder reads: node features [N, F], edge features [E, G] (None without message passing),
    edges [2, E] (sender, receiver), the graph of each node, the graph count, the normalised global context."""

    nodes: torch.Tensor
    edges: torch.Tensor | None
    edge_index: torch.Tensor | None
    batch: torch.Tensor
    num_graphs: int
    global_context: torch.Tensor | None


class LearnedSimulator(nn.Module):
    def __init__(self, config: ModelConfig, metadata: Metadata, noise_std: float):
        super().__init__()
        self.config = config
        self.dim = metadata.dim
        if config.connectivity_radius is None:
            raise ConfigError("model.connectivity_radius is unset: resolve the config against the dataset first "
                              "(config.resolve_for_dataset)")
        self.radius = float(config.connectivity_radius)
        # The release gives every particle its wall distances and a type embedding (model.wall_features,
        # model.type_embedding); the other settings follow the dataset (an import that does not know its
        # types counts as several).
        self.use_walls = config.wall_features == "always" or bool(metadata.walls)
        self.use_type_embedding = config.type_embedding == "always" or metadata.num_particle_types != 1
        self.context_size = metadata.context_size
        self.absolute = config.position_encoding == "absolute"

        def buffer(name: str, values: list[float]) -> None:
            self.register_buffer(name, torch.tensor(values, dtype=torch.float32))

        sigma2 = noise_std**2
        buffer("vel_mean", metadata.vel_mean)
        buffer("vel_std", [(s**2 + sigma2) ** 0.5 for s in metadata.vel_std])
        buffer("acc_mean", metadata.acc_mean)
        buffer("acc_std", [(s**2 + sigma2) ** 0.5 for s in metadata.acc_std])
        buffer("bounds", metadata.bounds)
        if self.context_size:
            buffer("context_mean", metadata.context_mean)
            buffer("context_std", [max(s, CONTEXT_STD_FLOOR) for s in metadata.context_std])
        if config.gravity_bias:
            if metadata.gravity is None:
                raise ConfigError("model.gravity_bias: the dataset's metadata.json has no 'gravity' field")
            buffer("gravity", metadata.gravity)

        num_velocities = config.input_sequence_length - 1
        node_in = num_velocities * self.dim
        node_in += 2 * self.dim if self.use_walls else 0
        node_in += self.dim if self.absolute else 0
        node_in += self.context_size
        if self.use_type_embedding:
            self.type_embedding = nn.Embedding(NUM_PARTICLE_TYPES, config.particle_type_embedding_size)
            node_in += config.particle_type_embedding_size
        edge_in = 2 * self.dim if self.absolute else self.dim + 1
        self.network = EncodeProcessDecode(
            node_in, edge_in, self.dim, latent_size=config.latent_size, hidden_size=config.mlp_hidden_size,
            hidden_layers=config.mlp_hidden_layers, message_passing_steps=config.message_passing_steps,
            shared_processor=config.shared_processor, global_latent=config.global_latent,
            global_in=self.context_size, linear_encoder_decoder=config.linear_encoder_decoder,
            aggregate=config.aggregate)
        if config.init == "sonnet":
            sonnet_init_(self)

    # What rollouts, evaluation and monitors read of any simulator (GNS, CConv, DPI alike).
    architecture = "gns"
    # Optional (rollouts ask with getattr): `predict_next_position(..., moving_only=True)` skips the work
    # of particles whose predictions the caller overwrites (kinematic ones).
    predicts_moving_only = True
    # Optional too: `predict_next_position(..., static_encodings=StaticEncodings(static))` reuses the encoder's
    # latents of never-moving particles and the edges among them across a rollout's steps.
    caches_static_encodings = True

    @property
    def input_sequence_length(self) -> int:
        """Positions in an input window: rollouts start after this many ground-truth frames."""
        return self.config.input_sequence_length

    @property
    def uses_edges(self) -> bool:
        return self.network.uses_edges

    @property
    def neighbour_backend(self) -> str:
        return self.config.neighbour_backend

    @property
    def self_edges(self) -> bool:
        return self.config.self_edges

    @property
    def normalisation(self) -> features.Normalisation:
        return features.Normalisation(
            self.vel_mean, self.vel_std, self.acc_mean, self.acc_std,
            getattr(self, "context_mean", None), getattr(self, "context_std", None))

    def build_graph(self, position: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        return radius_graph(position, self.radius, batch, backend=self.config.neighbour_backend,
                            self_edges=self.config.self_edges)

    def forward(self, window: torch.Tensor, particle_type: torch.Tensor, batch: torch.Tensor | None = None,
                context: torch.Tensor | None = None, edge_index: torch.Tensor | None = None,
                bounds: torch.Tensor | None = None, moving_only: bool = False,
                static_encodings: StaticEncodings | None = None) -> torch.Tensor:
        """Normalised acceleration [N, D] for a window [N, W, D] of positions.

        batch [N]: graph index per particle (None: one graph); context [B, C]: raw global context per
        graph; edge_index: precomputed edges for the window's last positions (searched when None);
        bounds [D, 2]: the scene's walls when they differ from the training data's (a larger arena).
        moving_only: decode only the particles that are predicted (not kinematic): kinematic ones get zero
        acceleration (a constant-velocity step), which callers overwrite with the data. Their decoder and
        last node update, and the last block's messages into them, are skipped (`EncodeProcessDecode`).
        static_encodings: one rollout's cache of the encoder's latents of particles that never move and of
        the edges among them (`model/static_encodings.py`); the encoders then run outside the network.
        """
        inputs = self.graph_inputs(window, particle_type, batch, context, edge_index, bounds)
        nodes, edges, encoded = inputs.nodes, inputs.edges, static_encodings is not None
        if static_encodings is not None:
            nodes = static_encodings.nodes(nodes, self.network.node_encoder)
            if edges is not None and self.network.uses_edges:
                edges = static_encodings.edges(edges, inputs.edge_index, self.network.edge_encoder)
        outputs = into = None
        if moving_only:
            moving = ~kinematic_mask(particle_type)
            if not bool(moving.all()):
                outputs = moving.nonzero()[:, 0]
                if inputs.edge_index is not None and self.network.uses_edges:
                    into = moving.index_select(0, inputs.edge_index[1]).nonzero()[:, 0]
        out = self.network(nodes, edges, inputs.edge_index, inputs.batch, inputs.num_graphs,
                           inputs.global_context, outputs, into, encoded)
        if self.config.gravity_bias:  # the network predicts the deviation from free fall
            out = out + (self.gravity - self.acc_mean) / self.acc_std
        if outputs is not None:
            decoded = out
            out = (-self.acc_mean / self.acc_std).to(decoded.dtype).expand(window.shape[0], -1).clone()
            out[outputs] = decoded  # the rest: the normalised zero acceleration
        return out

    def graph_inputs(self, window: torch.Tensor, particle_type: torch.Tensor, batch: torch.Tensor | None = None,
                     context: torch.Tensor | None = None, edge_index: torch.Tensor | None = None,
                     bounds: torch.Tensor | None = None) -> GraphInputs:
        """The encoder's input graph (Sec. 3.2, App. B.2): node and edge features and the edges; arguments
        as `forward`'s."""
        bounds = self.bounds if bounds is None else bounds
        n = window.shape[0]
        if batch is None:
            batch = torch.zeros(n, dtype=torch.long, device=window.device)
        # Only the global-latent ablation needs the graph count; reading it syncs a GPU, so skip it otherwise.
        num_graphs = int(batch[-1]) + 1 if n and self.config.global_latent else 1
        uses_edges = self.network.uses_edges
        if edge_index is None and uses_edges:
            edge_index = self.build_graph(window[:, -1], batch)
        norm = self.normalisation
        node_context = global_context = None
        if self.context_size:
            if context is None:
                raise ValueError("this simulator was built for a dataset with a global context; pass context")
            global_context = features.normalise_context(context, norm)
            node_context = global_context.index_select(0, batch)
        x = features.node_features(window, norm, bounds=bounds, radius=self.radius, walls=self.use_walls,
                                   absolute_positions=self.absolute, context=node_context,
                                   wall_range=self.config.wall_range)
        if self.use_type_embedding:
            x = torch.cat([x, self.type_embedding(particle_type)], dim=1)
        e = (features.edge_features(window[:, -1], edge_index, self.radius, absolute_positions=self.absolute,
                                    bounds=bounds) if uses_edges else None)
        return GraphInputs(x, e, edge_index, batch, num_graphs, global_context)

    def normalise_acceleration(self, acceleration: torch.Tensor) -> torch.Tensor:
        return (acceleration - self.acc_mean) / self.acc_std

    def denormalise_acceleration(self, normalised: torch.Tensor) -> torch.Tensor:
        return normalised * self.acc_std + self.acc_mean

    def predict_next_position(self, window: torch.Tensor, particle_type: torch.Tensor,
                              batch: torch.Tensor | None = None, context: torch.Tensor | None = None,
                              edge_index: torch.Tensor | None = None, bounds: torch.Tensor | None = None,
                              precision: str = "fp32", moving_only: bool = False,
                              static_encodings: StaticEncodings | None = None) -> torch.Tensor:
        """Next positions [N, D] of every particle, the one prediction path of evaluation and rollouts
        (callers put kinematic particles back from the data).

        The network runs under `precision` ("bf16": autocast; "fp64": the caller has cast the simulator,
        see `precision.network_dtype`); its output is cast back to the window's dtype, so denormalisation and
        the semi-implicit Euler step (Sec. 3.1) never round positions to bf16."""
        with autocast(window.device, precision):
            normalised = self(window, particle_type, batch, context, edge_index, bounds, moving_only,
                              static_encodings)
        return features.integrate(window, self.denormalise_acceleration(normalised.to(window.dtype)))


# What training, evaluation and rollouts may call, whatever the architecture (`model.architecture`): the GNS
# here, CConv (model/cconv.py), DPI-Net (model/dpi.py). Each exposes `dim`, `radius`, `bounds`,
# `input_sequence_length`, `uses_edges`, `neighbour_backend`, `self_edges`, `build_graph` and
# `predict_next_position(window, particle_type, batch, context, edge_index, bounds, precision)`; the training
# loop asks for each one's own loss (train/loop.py `batch_loss`).
Simulator = nn.Module


def kinematic_mask(particle_type: torch.Tensor) -> torch.Tensor:
    """True for kinematic (boundary/obstacle) particles: in the graph, never predicted or in the loss."""
    return particle_type == KINEMATIC_PARTICLE_TYPE
