"""Side by side with a peer implementation: geoelements/gns (the PyTorch port most GNS users start from).

`one_batch` feeds both codes one training batch of a gns-bench dataset with the same weights and the same
noise and compares, tensor by tensor, what each computes on the way to the loss (paper Sec. 3-4: node and edge
features, normalised inputs, target, prediction, loss, gradients). Agreement to float rounding says the two
implement one function; a disagreement names the first tensor where they part.

geoelements/gns is not a dependency: point `geo_source` at a checkout (the folder holding its `gns` package).
Its neighbour search goes through torch-cluster, which gns-bench does not need; the comparison hands it
gns-bench's search instead, in PyG's edge order convention (an edge set, so sums do not depend on the order).
"""

from __future__ import annotations

import dataclasses
import importlib
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from gns_bench.config import Config, resolve_for_dataset
from gns_bench.data.format import read_metadata
from gns_bench.data.windows import WindowSampler
from gns_bench.model.features import acceleration_from_next_position
from gns_bench.model.neighbours import radius_graph
from gns_bench.model.noise import noisy_training_pair
from gns_bench.model.simulator import LearnedSimulator, kinematic_mask
from gns_bench.train.checkpoints import build_simulator
from gns_bench.train.loop import load_training_split, step_inputs, training_loss


def import_geo(geo_source: str | Path):
    """geoelements/gns's `learned_simulator` module from a source checkout."""
    source = str(Path(geo_source).resolve())
    if source not in sys.path:
        sys.path.insert(0, source)
    module = importlib.import_module("gns.learned_simulator")

    def search(x, r, batch=None, loop=False, max_num_neighbors=32):  # PyG's radius_graph, gns-bench's search
        edges = radius_graph(x, r, batch, self_edges=loop)
        counts = torch.bincount(edges[1], minlength=x.shape[0])
        if int(counts.max()) > max_num_neighbors:  # the peer's cap would have dropped edges: say so
            raise ValueError(f"a particle has {int(counts.max())} neighbours, above the peer's cap "
                             f"max_num_neighbors={max_num_neighbors}")
        return edges  # [source, target]: PyG's flow, as radius_graph returns it

    module.radius_graph = search
    return module


def geo_simulator(geo, simulator: LearnedSimulator, metadata, noise_std: float):
    """The peer's simulator for the same dataset, built as its `train._get_simulator` builds it, with
    `simulator`'s weights (`copy_weights`)."""
    stats = {
        "acceleration": {"mean": torch.tensor(metadata.acc_mean, dtype=torch.float32),
                         "std": torch.sqrt(torch.tensor(metadata.acc_std) ** 2 + noise_std**2).float()},
        "velocity": {"mean": torch.tensor(metadata.vel_mean, dtype=torch.float32),
                     "std": torch.sqrt(torch.tensor(metadata.vel_std) ** 2 + noise_std**2).float()},
    }
    cfg = simulator.config
    dim = metadata.dim
    peer = geo.LearnedSimulator(
        particle_dimensions=dim, nnode_in=(cfg.input_sequence_length - 1) * dim + 2 * dim + 16, nedge_in=dim + 1,
        latent_dim=cfg.latent_size, nmessage_passing_steps=cfg.message_passing_steps,
        nmlp_layers=cfg.mlp_hidden_layers, mlp_hidden_dim=cfg.mlp_hidden_size,
        connectivity_radius=simulator.radius, boundaries=np.array(metadata.bounds), normalization_stats=stats,
        nparticle_types=9, particle_type_embedding_size=16, device="cpu")
    copy_weights(simulator, peer)
    return peer


def _mlp_pairs(ours: torch.nn.Sequential, theirs: torch.nn.Module, layer_norm: bool):
    """(our Linear/LayerNorm, their Linear/LayerNorm) in order; ours is build_mlp's Sequential."""
    our_linears = [m for m in ours if isinstance(m, torch.nn.Linear)]
    mlp = theirs[0] if layer_norm else theirs
    their_linears = [m for m in mlp if isinstance(m, torch.nn.Linear)]
    pairs = list(zip(our_linears, their_linears, strict=True))
    if layer_norm:
        pairs.append((ours[-1], theirs[1]))
    return pairs


def _permuted_first(weight: torch.Tensor, blocks: list[int], order: list[int]) -> torch.Tensor:
    """Our first-layer weight [H, sum(blocks)] with its column blocks reordered into the peer's input order."""
    parts = list(torch.split(weight, blocks, dim=1))
    return torch.cat([parts[i] for i in order], dim=1)


@torch.no_grad()
def copy_weights(simulator: LearnedSimulator, peer) -> None:
    """Give the peer our weights. Its edge MLP reads [receiver, sender, edge] where ours reads [edge, sender,
    receiver], and its node MLP [aggregated, node] where ours reads [node, aggregated]: the first layers'
    columns are permuted to match."""
    net, their = simulator.network, peer._encode_process_decode
    latent = simulator.config.latent_size
    peer._particle_type_embedding.weight.copy_(simulator.type_embedding.weight)
    pairs = (_mlp_pairs(net.node_encoder, their._encoder.node_fn, True)
             + _mlp_pairs(net.edge_encoder, their._encoder.edge_fn, True)
             + _mlp_pairs(net.decoder, their._decoder.node_fn, False))
    for block, stack in zip(net.processor, their._processor.gnn_stacks, strict=True):
        edge = _mlp_pairs(block.edge_mlp, stack.edge_fn, True)
        node = _mlp_pairs(block.node_mlp, stack.node_fn, True)
        edge[0][1].weight.copy_(_permuted_first(edge[0][0].weight, [latent] * 3, [2, 1, 0]))
        edge[0][1].bias.copy_(edge[0][0].bias)
        node[0][1].weight.copy_(_permuted_first(node[0][0].weight, [latent] * 2, [1, 0]))
        node[0][1].bias.copy_(node[0][0].bias)
        pairs += edge[1:] + node[1:]
    for ours, theirs in pairs:
        theirs.weight.copy_(ours.weight)
        theirs.bias.copy_(ours.bias)


@dataclass
class Comparison:
    name: str
    max_abs: float  # largest |ours - theirs|
    scale: float  # largest |ours|: what the difference is relative to

    @property
    def relative(self) -> float:
        return self.max_abs / self.scale if self.scale else self.max_abs


def _compare(name: str, ours: torch.Tensor, theirs: torch.Tensor) -> Comparison:
    if ours.shape != theirs.shape:
        raise ValueError(f"{name}: shapes differ, ours {tuple(ours.shape)} against {tuple(theirs.shape)}")
    ours, theirs = ours.detach().double(), theirs.detach().double()
    return Comparison(name, float((ours - theirs).abs().max()), float(ours.abs().max()))


def _sorted_edges(edge_index: torch.Tensor, values: torch.Tensor, n: int) -> torch.Tensor:
    """Edge rows in (receiver, sender) order, so two edge sets compare row by row."""
    order = torch.argsort(edge_index[1] * n + edge_index[0])
    return values[order]


def one_batch(config: Config, dataset_dir: str | Path, geo_source: str | Path, step: int = 0,
              seed: int = 0) -> list[Comparison]:
    """Both codes on step `step`'s batch and noise of a run of `config` on `dataset_dir`, the same weights
    (gns-bench's initialisation, seed `seed`): the comparisons, in the order the computation makes them."""
    geo = import_geo(geo_source)
    metadata = read_metadata(dataset_dir)
    config = resolve_for_dataset(config, metadata.default_connectivity_radius)
    torch.manual_seed(seed)
    simulator = build_simulator(config, metadata)
    if not isinstance(simulator, LearnedSimulator):
        raise ValueError("the peer comparison covers the GNS (model.architecture = 'gns')")
    peer = geo_simulator(geo, simulator, metadata, config.train.noise_std)
    trajectories = load_training_split(config, dataset_dir, metadata)
    sampler = WindowSampler(trajectories, config.model.input_sequence_length, config.train.seed)
    batch, noise, num_moving = step_inputs(sampler, step, config.train.batch_size, config.train.noise_std)
    n = batch.window.shape[0]
    counts = torch.bincount(batch.batch).tolist()
    window = batch.window.contiguous()  # the peer views [N, W, D] as [N, W * D]
    noisy, target_next = noisy_training_pair(window, batch.target, noise, config.train.position_correction)
    noisy = noisy.contiguous()
    out: list[Comparison] = []

    inputs = simulator.graph_inputs(noisy, batch.particle_type, batch.batch)
    their_nodes, their_edges_index, their_edges = peer._encoder_preprocessor(noisy, torch.tensor(counts),
                                                                            batch.particle_type)
    our_nodes = inputs.nodes
    out.append(_compare("node features (velocities, walls, type embedding)", our_nodes, their_nodes))
    out.append(_compare("edge features (displacement / R, distance / R)",
                        _sorted_edges(inputs.edge_index, inputs.edges, n),
                        _sorted_edges(their_edges_index, their_edges, n)))

    target = simulator.normalise_acceleration(acceleration_from_next_position(noisy, target_next))
    their_pred, their_target = peer.predict_accelerations(batch.target, noise, window, torch.tensor(counts),
                                                          batch.particle_type)
    out.append(_compare("target normalised acceleration", target, their_target))
    ours_pred = simulator(noisy, batch.particle_type, batch.batch)
    out.append(_compare("predicted normalised acceleration", ours_pred, their_pred))

    simulator.zero_grad()
    loss = training_loss(simulator, batch, noise, config.train.position_correction, num_moving=num_moving)
    loss.backward()
    moving = ~kinematic_mask(batch.particle_type)
    their_loss = ((their_pred - their_target) ** 2).sum(-1)[moving].sum() / moving.sum()
    peer.zero_grad()
    their_loss.backward()
    out.append(_compare("loss", loss.reshape(1), their_loss.reshape(1)))
    net, their = simulator.network, peer._encode_process_decode
    our_out = [m for m in net.decoder if isinstance(m, torch.nn.Linear)][-1]
    their_out = [m for m in their._decoder.node_fn if isinstance(m, torch.nn.Linear)][-1]
    out.append(_compare("gradient: decoder output layer", our_out.weight.grad, their_out.weight.grad))
    out.append(_compare("gradient: node encoder first layer", net.node_encoder[0].weight.grad,
                        their._encoder.node_fn[0][0].weight.grad))
    latent = config.model.latent_size
    ours_edge = net.processor[0].edge_mlp[0].weight.grad
    out.append(_compare("gradient: first block's edge MLP first layer",
                        _permuted_first(ours_edge, [latent] * 3, [2, 1, 0]),
                        their._processor.gnn_stacks[0].edge_fn[0][0].weight.grad))
    out.append(_compare("gradient: type embedding", simulator.type_embedding.weight.grad,
                        peer._particle_type_embedding.weight.grad))
    return out


def one_batch_markdown(results: dict[int, list[Comparison]], dataset_dir: str | Path, hardware: str) -> str:
    """The comparisons of `one_batch` at several steps as a markdown table."""
    steps = sorted(results)
    names = [c.name for c in results[steps[0]]]
    lines = [f"Dataset `{Path(dataset_dir).name}`, the paper's model (M = 10, latent 128), fp32, batch 2, noise "
             f"3e-4, gns-bench's initial weights (seed 0) copied into the peer; {hardware}.", "",
             "| tensor | " + " | ".join(f"step {s}: max abs diff (relative)" for s in steps) + " |",
             "|---|" + "---|" * len(steps)]
    for i, name in enumerate(names):
        cells = [f"{results[s][i].max_abs:.2e} ({results[s][i].relative:.1e})" for s in steps]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    import argparse
    import json

    from gns_bench.config import load_config
    from gns_bench.tracking import hardware_description

    parser = argparse.ArgumentParser(description="gns-bench and geoelements/gns fed one batch with the same "
                                                 "weights: tensor by tensor")
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--geo", type=Path, required=True, help="a geoelements/gns checkout (holding gns/)")
    parser.add_argument("--steps", type=int, nargs="+", default=[0, 1, 7], help="which training steps' batches")
    parser.add_argument("--out", type=Path, default=None, help="write one_batch.md and one_batch.json here")
    args = parser.parse_args(argv)
    config = load_config(None, ["train.steps=10"])
    results = {step: one_batch(config, args.dataset, args.geo, step=step) for step in args.steps}
    text = one_batch_markdown(results, args.dataset, hardware_description("cpu"))
    print(text)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "one_batch.md").write_text(text)
        payload = {str(step): [dataclasses.asdict(c) for c in comparisons] for step, comparisons in results.items()}
        (args.out / "one_batch.json").write_text(json.dumps(payload, indent=1) + "\n")


if __name__ == "__main__":
    main()
