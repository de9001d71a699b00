"""The straightforward PyG port, as a speed baseline: MessagePassing with concatenated edge-MLP inputs.

Same function and parameters as `gns_bench.model.network.InteractionNetwork` (the state dicts load into
each other); only the first edge layer differs in how it is computed: [e, v_sender, v_receiver] is
gathered and concatenated per edge before one matmul, as a plain `MessagePassing.message` does.
"""

from __future__ import annotations

import copy

import torch
from torch_geometric.nn import MessagePassing

from gns_bench.model.network import InteractionNetwork, build_mlp
from gns_bench.model.simulator import LearnedSimulator


class ConcatInteractionNetwork(MessagePassing):
    def __init__(self, latent_size: int, hidden_size: int, hidden_layers: int, aggregate_messages: bool = True):
        super().__init__(aggr="sum")
        self.latent_size = latent_size
        self.aggregate_messages = aggregate_messages  # as InteractionNetwork's: sum m, or the updated e + m
        self.edge_mlp = build_mlp(3 * latent_size, hidden_size, hidden_layers, latent_size, layer_norm=True)
        self.node_mlp = build_mlp(2 * latent_size, hidden_size, hidden_layers, latent_size, layer_norm=True)
        self._new_edges: torch.Tensor | None = None

    def message(self, x_i: torch.Tensor, x_j: torch.Tensor, edge_attr: torch.Tensor) -> torch.Tensor:
        # PyG: x_j is the source (sender), x_i the target (receiver) of each edge.
        messages = self.edge_mlp(torch.cat([edge_attr, x_j, x_i], dim=1))
        self._new_edges = edge_attr + messages
        return messages if self.aggregate_messages else self._new_edges

    def forward(self, nodes: torch.Tensor, edges: torch.Tensor, edge_index: torch.Tensor, globals_=None,
                node_graph=None, update_globals: bool = True):
        aggregated = self.propagate(edge_index, x=nodes, edge_attr=edges)
        new_edges, self._new_edges = self._new_edges, None
        return nodes + self.node_mlp(torch.cat([nodes, aggregated], dim=1)), new_edges, globals_


def concatenated_baseline(simulator: LearnedSimulator) -> LearnedSimulator:
    """A copy of `simulator` whose processor blocks run as plain PyG MessagePassing (same weights)."""
    if simulator.config.global_latent:
        raise ValueError("the baseline covers the paper's processor, without a global latent")
    baseline = copy.deepcopy(simulator)
    blocks = baseline.network.processor
    for index, block in enumerate(blocks):
        assert isinstance(block, InteractionNetwork)
        hidden_layers = sum(isinstance(m, torch.nn.ReLU) for m in block.edge_mlp)
        replacement = ConcatInteractionNetwork(block.latent_size, block.edge_mlp[0].out_features, hidden_layers,
                                               block.aggregate_messages)
        replacement.load_state_dict({k: v for k, v in block.state_dict().items() if not k.startswith("global")})
        blocks[index] = replacement.to(next(block.parameters()).device)
    return baseline
