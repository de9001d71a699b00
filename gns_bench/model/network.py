"""Encode-process-decode graph network (paper Sec. 3.2 and App. A; Battaglia et al. 2018).

  encoder    v0 = eps_v(x_i), e0 = eps_e(r_ij)                         MLP + LayerNorm
  processor  M interaction-network blocks, each with its own weights (or one shared block):
               m_ij  = phi_e([e_ij, v_sender, v_receiver (, u)])           the message
               e'_ij = e_ij + m_ij
               v'_i  = v_i  + phi_v([v_i, sum_{j -> i} m_ij (, u)])
               u'    = u    + phi_u([u, mean v', mean e'])              (global-latent ablation only)
  decoder    y_i = delta_v(v_i^M)                                         MLP, no LayerNorm

The node update sums the messages m_ij, as the release does: there each block is graph_nets'
InteractionNetwork (whose node block reads the edge block's outputs) with the residuals added after it
(graph_network.py, `_process_step`). `aggregate="updated_edges"` sums e'_ij = e_ij + m_ij instead, which is
what gns-bench did before it followed the release; checkpoints from then load with it (config.LEGACY_MODEL_VALUES).
`sonnet_init_` gives the release's initial weights (Sonnet 1.x `Linear` and `tf.get_variable`).

The first layer of phi_e is applied as per-node projections gathered per edge,
W [e, v_s, v_r] = W_e e + (W_s v)[s] + (W_r v)[r], which is the same function as the concatenated
form with fewer FLOPs (E >> N); the weights are stored as one Linear so both forms share parameters.
Sum aggregation is an `index_add` (backward: an `index_select`). On this CPU (idle, 28.6k x 128 rows) a
segment sum over receiver-sorted edges took 2.7 ms in fp32 and 7.2 ms in bf16 against 0.55 ms, and PyG's
`scatter` broadcasts its index so that its backward is a `gather` (2.7 ms) rather than an `index_select`
(0.4 ms); `gns-bench bench` measures the whole step.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch_geometric.utils import scatter


def build_mlp(in_size: int, hidden_size: int, hidden_layers: int, out_size: int, *,
              layer_norm: bool) -> nn.Sequential:
    """`hidden_layers` ReLU layers of `hidden_size`, a linear output, then LayerNorm if asked."""
    layers: list[nn.Module] = []
    size = in_size
    for _ in range(hidden_layers):
        layers += [nn.Linear(size, hidden_size), nn.ReLU(inplace=True)]
        size = hidden_size
    layers.append(nn.Linear(size, out_size))
    if layer_norm:
        layers.append(nn.LayerNorm(out_size))
    return nn.Sequential(*layers)


def sonnet_init_(module: nn.Module) -> nn.Module:
    """The release's initial weights, in place, for every Linear and Embedding inside `module`.

    Sonnet 1.x's `Linear` draws W from a normal of std 1/sqrt(fan_in) truncated at two stds and sets b = 0
    (PyTorch: uniform of std 0.58/sqrt(fan_in), uniform biases); the release's type embedding is a plain
    `tf.get_variable`, whose default is Glorot-uniform (PyTorch: N(0, 1)). LayerNorm starts at scale 1,
    offset 0 in both. Early training speed depends on this, and CPU budgets are early training.
    """
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            std = 1.0 / math.sqrt(layer.in_features)
            nn.init.trunc_normal_(layer.weight, std=std, a=-2.0 * std, b=2.0 * std)
            if layer.bias is not None:
                nn.init.zeros_(layer.bias)
        elif isinstance(layer, nn.Embedding):
            nn.init.xavier_uniform_(layer.weight)
    return module


def aggregate(edges: torch.Tensor, receivers: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """Sum of incoming edge latents per node."""
    return edges.new_zeros(num_nodes, edges.shape[1]).index_add_(0, receivers, edges)


class InteractionNetwork(nn.Module):
    """One GN block with residual edge and node updates and sum aggregation (no global, unless asked)."""

    def __init__(self, latent_size: int, hidden_size: int, hidden_layers: int, global_latent: bool,
                 updates_globals: bool = True, aggregate_messages: bool = True):
        super().__init__()
        g = latent_size if global_latent else 0
        self.latent_size = latent_size
        self.aggregate_messages = aggregate_messages  # False: sum the updated edges e + m (see module doc)
        self.global_latent = global_latent
        self.edge_mlp = build_mlp(3 * latent_size + g, hidden_size, hidden_layers, latent_size,
                                  layer_norm=True)
        self.node_mlp = build_mlp(2 * latent_size + g, hidden_size, hidden_layers, latent_size,
                                  layer_norm=True)
        self.global_mlp = (build_mlp(3 * latent_size, hidden_size, hidden_layers, latent_size,
                                     layer_norm=True) if global_latent and updates_globals else None)

    def edge_update(self, nodes: torch.Tensor, edges: torch.Tensor, edge_index: torch.Tensor,
                    edge_globals: torch.Tensor | None) -> torch.Tensor:
        """phi_e([e, v_sender, v_receiver (, u)]) with the first layer split per node (see module doc)."""
        first, rest = self.edge_mlp[0], self.edge_mlp[1:]
        size = self.latent_size
        weight = first.weight  # [H, 3L (+L)]: columns for [e, v_sender, v_receiver (, u)]
        hidden = torch.addmm(first.bias, edges, weight[:, :size].T)
        # Per-node projections (N x L x H each, cheap) gathered per edge: contiguous rows for index_select.
        # In-place adds: addmm's backward does not need its output, and no [E, H] buffer is allocated.
        hidden.add_((nodes @ weight[:, size:2 * size].T).index_select(0, edge_index[0]))
        hidden.add_((nodes @ weight[:, 2 * size:3 * size].T).index_select(0, edge_index[1]))
        if edge_globals is not None:
            hidden.add_(edge_globals @ weight[:, 3 * size:].T)
        return rest(hidden)

    def forward(self, nodes: torch.Tensor, edges: torch.Tensor, edge_index: torch.Tensor,
                globals_: torch.Tensor | None = None, node_graph: torch.Tensor | None = None,
                update_globals: bool = True
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        node_globals = edge_globals = None
        if self.global_latent:
            node_globals = globals_.index_select(0, node_graph)
            edge_globals = node_globals.index_select(0, edge_index[1])
        messages = self.edge_update(nodes, edges, edge_index, edge_globals)
        new_edges = edges + messages
        aggregated = aggregate(messages if self.aggregate_messages else new_edges, edge_index[1], nodes.shape[0])
        node_inputs = [nodes, aggregated] + ([node_globals] if self.global_latent else [])
        new_nodes = nodes + self.node_mlp(torch.cat(node_inputs, dim=1))
        new_globals = globals_
        if self.global_mlp is not None and update_globals:
            num_graphs = globals_.shape[0]
            mean_nodes = scatter(new_nodes, node_graph, dim=0, dim_size=num_graphs, reduce="mean")
            edge_graph = node_graph.index_select(0, edge_index[1])
            mean_edges = scatter(new_edges, edge_graph, dim=0, dim_size=num_graphs, reduce="mean")
            new_globals = globals_ + self.global_mlp(torch.cat([globals_, mean_nodes, mean_edges], dim=1))
        return new_nodes, new_edges, new_globals

    def nodes_of(self, wanted: torch.Tensor, into: torch.Tensor, nodes: torch.Tensor, edges: torch.Tensor,
                 edge_index: torch.Tensor, globals_: torch.Tensor | None = None,
                 node_graph: torch.Tensor | None = None) -> torch.Tensor:
        """The updated latents [P, L] of the nodes `wanted` (indices [P]) alone, as the last block of
        the processor needs them: only the edges `into` them (indices, in edge order) carry messages, no edge or
        global is updated. The same numbers as `forward`'s rows (sums over the same edges in the same order);
        the matrix products, on fewer rows, may round differently."""
        sub_index, sub_edges = edge_index.index_select(1, into), edges.index_select(0, into)
        node_globals = edge_globals = None
        if self.global_latent:
            node_globals = globals_.index_select(0, node_graph)
            edge_globals = node_globals.index_select(0, sub_index[1])
        messages = self.edge_update(nodes, sub_edges, sub_index, edge_globals)
        summed = messages if self.aggregate_messages else sub_edges + messages
        aggregated = aggregate(summed, sub_index[1], nodes.shape[0]).index_select(0, wanted)
        own = nodes.index_select(0, wanted)
        node_inputs = [own, aggregated] + ([node_globals.index_select(0, wanted)] if self.global_latent else [])
        return own + self.node_mlp(torch.cat(node_inputs, dim=1))


class EncodeProcessDecode(nn.Module):
    def __init__(self, node_in: int, edge_in: int, out_size: int, *, latent_size: int = 128,
                 hidden_size: int = 128, hidden_layers: int = 2, message_passing_steps: int = 10,
                 shared_processor: bool = False, global_latent: bool = False, global_in: int = 0,
                 linear_encoder_decoder: bool = False, aggregate: str = "messages"):
        super().__init__()
        if linear_encoder_decoder:
            self.node_encoder: nn.Module = nn.Linear(node_in, latent_size)
            self.edge_encoder: nn.Module = nn.Linear(edge_in, latent_size)
            self.decoder: nn.Module = nn.Linear(latent_size, out_size)
        else:
            self.node_encoder = build_mlp(node_in, hidden_size, hidden_layers, latent_size, layer_norm=True)
            self.edge_encoder = build_mlp(edge_in, hidden_size, hidden_layers, latent_size, layer_norm=True)
            self.decoder = build_mlp(latent_size, hidden_size, hidden_layers, out_size, layer_norm=False)
        self.global_latent = global_latent
        if global_latent:
            # u0 from the global context when there is one, else a learned constant.
            self.global_encoder = (build_mlp(global_in, hidden_size, hidden_layers, latent_size,
                                             layer_norm=True) if global_in else None)
            self.global_constant = nn.Parameter(torch.zeros(latent_size)) if not global_in else None
        if aggregate not in ("messages", "updated_edges"):
            raise ValueError(f"aggregate: expected 'messages' or 'updated_edges', got {aggregate!r}")
        aggregate_messages = aggregate == "messages"
        if message_passing_steps == 0:  # M = 0: a per-particle MLP, edges play no part
            self.processor = nn.ModuleList()
            self.schedule = []
        elif shared_processor:
            self.processor = nn.ModuleList(
                [InteractionNetwork(latent_size, hidden_size, hidden_layers, global_latent,
                                    aggregate_messages=aggregate_messages)])
            self.schedule = [0] * message_passing_steps
        else:
            # The last block's global update would feed nothing (the decoder reads nodes): not built.
            self.processor = nn.ModuleList(
                InteractionNetwork(latent_size, hidden_size, hidden_layers, global_latent,
                                   updates_globals=step < message_passing_steps - 1,
                                   aggregate_messages=aggregate_messages)
                for step in range(message_passing_steps))
            self.schedule = list(range(message_passing_steps))

    @property
    def uses_edges(self) -> bool:
        return bool(self.schedule)

    def forward(self, node_features: torch.Tensor, edge_features: torch.Tensor | None, edge_index: torch.Tensor,
                node_graph: torch.Tensor | None = None, num_graphs: int = 1,
                global_features: torch.Tensor | None = None, outputs: torch.Tensor | None = None,
                output_edges: torch.Tensor | None = None, encoded: bool = False) -> torch.Tensor:
        """Decoded outputs [N, out] of every node, or [P, out] of the nodes `outputs` (indices [P]) alone: the
        last block then updates only those nodes from `output_edges`, the edges into them (indices, in edge
        order), and the decoder reads only them (`InteractionNetwork.nodes_of`). The caller finds both (data-
        dependent shapes stay out of a compiled network). `encoded`: the node and edge inputs are the
        encoders' latents already (`model/static_encodings.py` reuses some across rollout steps)."""
        nodes = node_features if encoded else self.node_encoder(node_features)
        if not self.schedule:
            return self.decoder(nodes if outputs is None else nodes.index_select(0, outputs))
        edges = edge_features if encoded else self.edge_encoder(edge_features)
        globals_ = None
        if self.global_latent:
            if self.global_encoder is not None:
                globals_ = self.global_encoder(global_features)
            else:
                globals_ = self.global_constant.expand(num_graphs, -1)
        schedule = self.schedule if outputs is None else self.schedule[:-1]
        for step, index in enumerate(schedule):
            nodes, edges, globals_ = self.processor[index](nodes, edges, edge_index, globals_, node_graph,
                                                           update_globals=step < len(self.schedule) - 1)
        if outputs is not None:
            nodes = self.processor[self.schedule[-1]].nodes_of(outputs, output_edges, nodes, edges, edge_index,
                                                               globals_, node_graph)
        return self.decoder(nodes)
