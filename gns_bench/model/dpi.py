"""DPI-Net (Li, Wu, Tedrake, Tenenbaum, Torralba, ICLR 2019), the BOXBATH baseline of the GNS paper's Sec. 5.5.

Written from the authors' code (github.com/YunzhuLi/DPI-Net: models.py, data.py, train.py, eval.py); no
code is copied. What it is there, for BoxBath:

Graph (data.py `prepare_input`, `make_hierarchy`), rebuilt every step from the current positions:
  leaves   one node per particle;
  stage 0  leaf -> leaf within `neighbor_radius` = 0.08 (FleX units), pstep = 2 propagation steps. A fluid
           particle receives from every particle in range, itself included (the ball query finds it); a
           rigid particle receives only from particles of *other* objects: inside the cube, information
           moves through the hierarchy;
  roots    the cube's particles at frame 0 are split by k-means into root_num = 8 clusters (data.py
           `gen_PyFleX`), one root node per cluster, whose state is the mean of its leaves';
  stage 1  leaf -> root, each leaf to its cluster's root, 1 step;
  stage 2  root -> root, every ordered pair of the object's roots, each root with itself too (with a
           single root: one self-relation), root_pstep = pstep = 2 steps;
  stage 3  root -> leaf, each root back to its own leaves, 1 step.
Network (models.py `DPINet`): per stage its own particle encoder (2 layers, ReLU), relation encoder
(3 layers, ReLU), relation propagator and particle propagator (1 layer each, the latter residual:
e' = ReLU(W [encoding, sum of incoming relation effects] + e)); widths nf_relation = 300,
nf_particle = nf_effect = 200. Node input: attributes [rigid, fluid, root] plus, for the cube's
particles, their state minus the cube's mean state, then the state [position, velocity], both normalised
by the dataset's mean and std. Relation input: [attr_r, attr_s, state_r, state_s]: absolute states (the
difference is computed but unused), so the model is not translation invariant.
Heads (MLPs with two hidden layers of 200): fluid particles get a normalised velocity from their effect;
the cube gets one rigid motion (7 numbers) from the mean effect of its particles: a quaternion (normalised)
and a translation, turned into the velocities of its particles about their centroid: rigid by
construction.
Loss and training (train.py): MSE between predicted and true normalised next velocities of all
particles; Adam, lr 1e-4, beta1 0.9, batch 1 with gradients of 2 samples accumulated (forward_times),
ReduceLROnPlateau(0.8, patience 3) on the validation loss; no input noise; one past velocity (n_his 0).
The rigid projection (Kabsch onto the frame-0 cube, data.py `gen_PyFleX`) is applied to the
ground-truth cube when the data is made; it is not in the training loss, and eval.py does not apply it
to predictions (they are rigid already).

Ours: `rigid_projection` is also applied to every prediction (onto the rest shape: the rigid particles
of the window's first frame), which keeps a rollout's cube exactly rigid as the authors' ground truth is.
Other choices are documented on `DPIConfig` and where they happen.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn
from torch.nn import functional as F

from gns_bench.config import ConfigError, DPIConfig
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, NUM_PARTICLE_TYPES, Metadata
from gns_bench.model.neighbours import radius_graph
from gns_bench.model.noise import noisy_training_pair
from gns_bench.model.precision import autocast

RIGID_PARTICLE_TYPE = 0  # datasets/boxbath.toml: particle_types.rigid
RIGID_HEADS = ("transform", "velocity")
STAGES = ("leaf_to_leaf", "leaf_to_root", "root_to_root", "root_to_leaf")
KMEANS_ITERATIONS = 30
KMEANS_STARTS = 16


def rigid_projection(predicted: torch.Tensor, rest_shape: torch.Tensor) -> torch.Tensor:
    """The rest shape [K, D] moved by the proper rotation and translation that best fit `predicted` [K, D]
    in least squares (Kabsch/Umeyama without scaling; D = 2 or 3).

    With H = sum_k q_k p_k^T over centred rest q and predicted p, H = U S V^T, the best rotation is
    R = V diag(1, .., d) U^T with d = det(V U^T), which keeps det R = +1 (no reflection), and the best
    translation maps centroid to centroid. Computed in float64; returns `predicted`'s dtype. Its
    gradient is undefined where singular values coincide: use it on predictions, not inside a loss.
    """
    if predicted.ndim != 2 or predicted.shape != rest_shape.shape:
        raise ValueError(f"expected two [K, D] tensors, got {tuple(predicted.shape)} and {tuple(rest_shape.shape)}")
    p = predicted.to(torch.float64)
    q = rest_shape.to(torch.float64)
    p_centre, q_centre = p.mean(dim=0), q.mean(dim=0)
    covariance = (q - q_centre).T @ (p - p_centre)
    u, _, vh = torch.linalg.svd(covariance)
    v = vh.T
    flip = torch.ones(p.shape[1], dtype=p.dtype, device=p.device)
    flip[-1] = torch.sign(torch.linalg.det(v @ u.T))
    rotation = (v * flip) @ u.T
    return ((q - q_centre) @ rotation.T + p_centre).to(predicted.dtype)


def kmeans_labels(points: torch.Tensor, k: int) -> torch.Tensor:
    """Cluster [K, D] points into at most k groups; labels [K] in 0..k'-1 (k' <= k, empty clusters dropped).

    Deterministic (the authors ran sklearn's MiniBatchKMeans with random_state 0): Lloyd iterations from
    KMEANS_STARTS farthest-point seedings, each started at another point, run side by side; the lowest
    inertia wins. (One seeding is not enough: on a 4^3 cube it can settle in slabs instead of octants.)
    """
    x = points.detach().to(torch.float64)
    k = min(k, x.shape[0])
    starts = torch.linspace(0, x.shape[0] - 1, min(KMEANS_STARTS, x.shape[0]), device=x.device).round().long()
    chosen = [starts]
    nearest = (x[None] - x[starts][:, None]).square().sum(dim=2)  # [starts, K]
    for _ in range(k - 1):
        chosen.append(nearest.argmax(dim=1))
        nearest = torch.minimum(nearest, (x[None] - x[chosen[-1]][:, None]).square().sum(dim=2))
    centres = x[torch.stack(chosen, dim=1)]  # [starts, k, D]
    xs = x.expand(len(starts), -1, -1)
    for _ in range(KMEANS_ITERATIONS):
        member = F.one_hot(torch.cdist(xs, centres).argmin(dim=2), k).to(x.dtype)  # [starts, K, k]
        count = member.sum(dim=1)[..., None]
        updated = torch.where(count > 0, member.transpose(1, 2) @ x / count.clamp(min=1), centres)
        if torch.equal(updated, centres):
            break
        centres = updated
    distance = torch.cdist(xs, centres)
    best = int(distance.min(dim=2).values.square().sum(dim=1).argmin())
    return torch.unique(distance[best].argmin(dim=1), return_inverse=True)[1]


class RigidBodies(NamedTuple):
    """The rigid particles of a batch: their indices [K], the body of each [K] in 0..count-1."""

    leaves: torch.Tensor
    body: torch.Tensor
    count: int


def rigid_bodies(particle_type: torch.Tensor, batch: torch.Tensor | None = None,
                 rigid_body: torch.Tensor | None = None) -> RigidBodies:
    """Group rigid particles (type 0) into bodies: one per graph of the batch, or, with `rigid_body` [N]
    (a body id per particle, any value for the others), one per (graph, id)."""
    leaves = (particle_type == RIGID_PARTICLE_TYPE).nonzero()[:, 0]
    key = torch.zeros_like(leaves) if batch is None else batch.index_select(0, leaves).long()
    if rigid_body is not None:
        ids = rigid_body.index_select(0, leaves).long()
        ids = ids - ids.min() if ids.numel() else ids
        key = key * (int(ids.max()) + 1 if ids.numel() else 1) + ids
    unique, body = torch.unique(key, return_inverse=True)
    return RigidBodies(leaves, body, int(unique.numel()))


class Hierarchy(NamedTuple):
    """Root nodes (numbered after the N leaves) and the relations of stages 1-3, edges as (sender, receiver)."""

    num_roots: int
    root_members: torch.Tensor  # [K] the root of each rigid leaf (in RigidBodies.leaves order)
    root_body: torch.Tensor  # [R] the body of each root
    leaf_to_root: torch.Tensor  # [2, K]
    root_to_root: torch.Tensor  # [2, sum over bodies of k_b^2]: all ordered pairs of a body's roots, self included
    root_to_leaf: torch.Tensor  # [2, K]


def build_hierarchy(rest_shape: torch.Tensor, bodies: RigidBodies, num_leaves: int, roots_per_body: int) -> Hierarchy:
    """One root per k-means cluster of each body's rest shape [K, D] (rows in `bodies.leaves` order)."""
    device = bodies.leaves.device
    root_members = torch.zeros_like(bodies.leaves)
    root_body, pairs, offset = [], [], num_leaves
    for b in range(bodies.count):
        members = (bodies.body == b).nonzero()[:, 0]
        labels = kmeans_labels(rest_shape.index_select(0, members), roots_per_body).to(device)
        k = int(labels.max()) + 1
        root_members[members] = offset + labels
        roots = torch.arange(offset, offset + k, device=device)
        pairs.append(torch.stack([roots.repeat_interleave(k), roots.repeat(k)]))
        root_body.append(torch.full((k,), b, dtype=torch.long, device=device))
        offset += k
    empty = torch.zeros((2, 0), dtype=torch.long, device=device)
    return Hierarchy(offset - num_leaves, root_members,
                     torch.cat(root_body) if root_body else torch.zeros(0, dtype=torch.long, device=device),
                     torch.stack([bodies.leaves, root_members]), torch.cat(pairs, dim=1) if pairs else empty,
                     torch.stack([root_members, bodies.leaves]))


def mlp(sizes: list[int], final_relu: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        layers.append(nn.Linear(a, b))
        if final_relu or i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class PropagationStage(nn.Module):
    """One stage of DPI-Net's multi-step propagation (the loop body of their `DPINet.forward`):
        relation encoding  c_k = f_R(attr_r, attr_s, state_r, state_s),   node encoding  c_i = f_O(attr_i, state_i)
        for `steps` steps: e_k = ReLU(W_R [c_k, e_r, e_s]);  e_i <- ReLU(W_O [c_i, sum_{k -> i} e_k] + e_i)
    for the stage's receiver nodes, all updated at once from the previous effects."""

    def __init__(self, attr_size: int, state_size: int, config: DPIConfig):
        super().__init__()
        nf_r, nf_p, nf_e = config.nf_relation, config.nf_particle, config.nf_effect
        self.particle_encoder = mlp([attr_size + state_size, nf_p, nf_e])
        self.relation_encoder = mlp([2 * attr_size + 2 * state_size, nf_r, nf_r, nf_r])
        self.relation_propagator = nn.Linear(nf_r + 2 * nf_e, nf_e)
        self.particle_propagator = nn.Linear(2 * nf_e, nf_e)

    def forward(self, effect: torch.Tensor, attr: torch.Tensor, state: torch.Tensor, edges: torch.Tensor,
                nodes: torch.Tensor, steps: int) -> torch.Tensor:
        """effect [M, F] of every node; edges [2, E] (sender, receiver); nodes: this stage's receivers."""
        senders, receivers = edges
        encoded = self.particle_encoder(torch.cat([attr[nodes], state[nodes]], dim=1))
        relation = self.relation_encoder(
            torch.cat([attr[receivers], attr[senders], state[receivers], state[senders]], dim=1))
        slot = torch.full((effect.shape[0],), -1, dtype=torch.long, device=effect.device)
        slot[nodes] = torch.arange(nodes.numel(), device=effect.device)
        receiver_slot = slot[receivers]
        # W_R [c_k, e_r, e_s] + b = (W_c c_k + b) + (W_r e)_r + (W_s e)_s: the encoding's term once for all steps,
        # the effects' terms per node before the gather (nodes are far fewer than relations). The same maths
        # as the concatenation, and the same parameters; BOXBATH training went from 2.07 to 3.27 steps/s (mean over
        # the same 75 steps; cpu tier, batch 2, bf16; AMD EPYC family 25, 2 threads).
        nf_r, nf_e = relation.shape[1], effect.shape[1]
        weight = self.relation_propagator.weight
        encoding_term = F.linear(relation, weight[:, :nf_r], self.relation_propagator.bias)
        effect_weight = torch.cat([weight[:, nf_r:nf_r + nf_e], weight[:, nf_r + nf_e:]])  # [2 nf_e, nf_e]
        for _ in range(steps):
            as_receiver, as_sender = F.linear(effect, effect_weight).split(nf_e, dim=1)
            relation_effect = F.relu(encoding_term + as_receiver[receivers] + as_sender[senders])
            incoming = relation_effect.new_zeros((nodes.numel(), relation_effect.shape[1]))
            incoming.index_add_(0, receiver_slot, relation_effect)
            updated = F.relu(self.particle_propagator(torch.cat([encoded, incoming], dim=1)) + effect[nodes])
            effect = effect.index_copy(0, nodes, updated.to(effect.dtype))
        return effect


class DPIGraph(NamedTuple):
    num_leaves: int
    leaf_edges: torch.Tensor  # [2, E] stage 0, already without a rigid body's relations to itself
    bodies: RigidBodies
    hierarchy: Hierarchy | None  # None without rigid particles: stage 0 only


class DPINetwork(nn.Module):
    """The four propagation stages and the two heads; inputs and outputs normalised."""

    def __init__(self, dim: int, attr_size: int, state_size: int, config: DPIConfig):
        super().__init__()
        self.config = config
        self.stages = nn.ModuleDict({name: PropagationStage(attr_size, state_size, config) for name in STAGES})
        nf = config.nf_effect
        self.particle_predictor = mlp([nf, nf, nf, dim], final_relu=False)
        # a rotation (a unit quaternion in 3D, a unit complex number in 2D) and a translation
        self.rigid_predictor = mlp([nf, nf, nf, (4 if dim == 3 else 2) + dim], final_relu=False)

    @property
    def uses_edges(self) -> bool:
        return True

    def forward(self, attr: torch.Tensor, state: torch.Tensor,
                graph: DPIGraph) -> tuple[torch.Tensor, torch.Tensor | None]:
        """attr, state [M, *] for the N leaves then the roots. Returns the particle head's normalised
        velocities [N, D] and the rigid head's motion parameters [bodies, P] (None without rigid bodies)."""
        n, c = graph.num_leaves, self.config
        effect = attr.new_zeros((attr.shape[0], c.nf_effect))
        leaves = torch.arange(n, device=attr.device)
        effect = self.stages["leaf_to_leaf"](effect, attr, state, graph.leaf_edges, leaves, c.pstep)
        h = graph.hierarchy
        if h is None:
            return self.particle_predictor(effect[:n]), None
        roots = torch.arange(n, n + h.num_roots, device=attr.device)
        effect = self.stages["leaf_to_root"](effect, attr, state, h.leaf_to_root, roots, 1)
        effect = self.stages["root_to_root"](effect, attr, state, h.root_to_root, roots, c.root_pstep)
        effect = self.stages["root_to_leaf"](effect, attr, state, h.root_to_leaf, graph.bodies.leaves, 1)
        body_effect = segment_mean(effect[graph.bodies.leaves], graph.bodies.body, graph.bodies.count)
        return self.particle_predictor(effect[:n]), self.rigid_predictor(body_effect)


def segment_mean(values: torch.Tensor, segment: torch.Tensor, count: int) -> torch.Tensor:
    sums = values.new_zeros((count, values.shape[1])).index_add(0, segment, values)
    sizes = torch.bincount(segment, minlength=count).clamp(min=1).to(values.dtype)
    return sums / sizes[:, None]


def rotation_matrices(params: torch.Tensor) -> torch.Tensor:
    """[B, 4] quaternions (w, x, y, z) or [B, 2] complex numbers (cos, sin), any norm -> rotations [B, D, D].

    The identity is added first: an untrained head (outputs near 0) starts near no rotation. It is a
    constant shift of the last layer's bias, not a change of the model (theirs normalises the raw output)."""
    if params.shape[1] == 2:
        c, s = (params + params.new_tensor([1.0, 0.0])).unbind(dim=1)
        r = torch.sqrt(c * c + s * s).clamp(min=1e-12)
        c, s = c / r, s / r
        return torch.stack([torch.stack([c, -s], dim=1), torch.stack([s, c], dim=1)], dim=1)
    q = params + params.new_tensor([1.0, 0.0, 0.0, 0.0])
    w, x, y, z = (q / q.norm(dim=1, keepdim=True).clamp(min=1e-12)).unbind(dim=1)
    rows = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    return torch.stack([torch.stack(row, dim=1) for row in rows], dim=1)


class DPISimulator(nn.Module):
    """DPI-Net as a simulator: positions in, normalised next velocities out, p' = p + v (dt = 1 frame)."""

    architecture = "dpi"

    def __init__(self, config: DPIConfig, metadata: Metadata, connectivity_radius: float,
                 input_sequence_length: int = 6):
        """`connectivity_radius`: the resolved `model.connectivity_radius` (the dataset's R unless set), scaled by
        `dpi.radius_scale`."""
        super().__init__()
        config.validate()
        self.config = config
        if input_sequence_length < config.n_his + 2:
            raise ConfigError(f"model.input_sequence_length: DPI reads n_his + 2 = {config.n_his + 2} frames, got "
                              f"{input_sequence_length}")
        # What rollouts and evaluation read of any simulator (model/simulator.py, `Simulator`).
        self.input_sequence_length = input_sequence_length
        self.uses_edges = True
        self.neighbour_backend, self.self_edges = config.neighbour_backend, config.self_edges
        self.dim = metadata.dim
        self.radius = float(config.radius_scale * connectivity_radius)

        def buffer(name: str, values: list[float] | list[list[float]]) -> None:
            self.register_buffer(name, torch.tensor(values, dtype=torch.float32))

        buffer("vel_mean", metadata.vel_mean)
        buffer("vel_std", [s if s > 0 else 1.0 for s in metadata.vel_std])  # as their `normalize`: std 0 -> 1
        buffer("bounds", metadata.bounds)
        # Their positions are normalised by the data's position mean and std; our metadata has none, so
        # the box's centre and half-span: positions in [-1, 1], and the walls at fixed inputs, which is how
        # the model knows them (it has no wall features).
        bounds = torch.tensor(metadata.bounds, dtype=torch.float32)
        self.register_buffer("position_centre", bounds.mean(dim=1))
        self.register_buffer("position_scale", (bounds[:, 1] - bounds[:, 0]) / 2)
        self.num_velocities = config.n_his + 1
        state_size = self.dim * (1 + self.num_velocities)
        attr_size = NUM_PARTICLE_TYPES + 1 + state_size  # type one-hot, root flag, offset to the body's mean
        self.network = DPINetwork(self.dim, attr_size, state_size, config)

    def build_graph(self, positions: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        """Leaf-to-leaf edges [2, E] (sender, receiver) within the radius, each particle with itself too."""
        return radius_graph(positions, self.radius, batch, backend=self.config.neighbour_backend,
                            self_edges=self.config.self_edges)

    def normalise_velocity(self, velocity: torch.Tensor) -> torch.Tensor:
        return (velocity - self.vel_mean) / self.vel_std

    def denormalise_velocity(self, normalised: torch.Tensor) -> torch.Tensor:
        return normalised * self.vel_std + self.vel_mean

    def graph(self, window: torch.Tensor, particle_type: torch.Tensor, batch: torch.Tensor | None,
              edge_index: torch.Tensor | None, rest_shape: torch.Tensor,
              rigid_body: torch.Tensor | None = None) -> DPIGraph:
        n = window.shape[0]
        if edge_index is None:
            edge_index = self.build_graph(window[:, -1], batch)
        bodies = rigid_bodies(particle_type, batch, rigid_body)
        body_of = torch.full((n,), -1, dtype=torch.long, device=window.device)
        body_of[bodies.leaves] = bodies.body
        sender_body, receiver_body = body_of[edge_index[0]], body_of[edge_index[1]]
        edges = edge_index[:, (receiver_body < 0) | (receiver_body != sender_body)]
        hierarchy = (build_hierarchy(rest_shape.index_select(0, bodies.leaves), bodies, n,
                                     self.config.roots_per_rigid_body) if bodies.count else None)
        return DPIGraph(n, edges, bodies, hierarchy)

    def node_inputs(self, window: torch.Tensor, particle_type: torch.Tensor,
                    graph: DPIGraph) -> tuple[torch.Tensor, torch.Tensor]:
        """Attributes and states [M, *] of the leaves then the roots (their data.py `prepare_input`)."""
        if window.shape[1] < self.num_velocities + 1:
            raise ValueError(f"a window of {window.shape[1]} frames; DPI-Net with n_his = {self.config.n_his} "
                             f"needs {self.num_velocities + 1}")
        n = window.shape[0]
        frames = window[:, -(self.num_velocities + 1):]
        velocity = (frames[:, 1:] - frames[:, :-1]).flip(1)  # current velocity first, as theirs
        state = torch.cat([(frames[:, -1] - self.position_centre) / self.position_scale,
                           self.normalise_velocity(velocity).reshape(n, -1)], dim=1)
        attr = torch.cat([F.one_hot(particle_type.long(), NUM_PARTICLE_TYPES).to(state.dtype),
                          state.new_zeros((n, 1)), torch.zeros_like(state)], dim=1)
        h = graph.hierarchy
        if h is None:
            return attr, state
        leaves, body = graph.bodies.leaves, graph.bodies.body
        offset = state[leaves] - segment_mean(state[leaves], body, graph.bodies.count)[body]
        attr = attr.index_copy(0, leaves, torch.cat([attr[leaves, :NUM_PARTICLE_TYPES + 1], offset], dim=1))
        members = h.root_members - n
        root_state = segment_mean(state[leaves], members, h.num_roots)
        root_attr = segment_mean(attr[leaves], members, h.num_roots)
        root_attr[:, NUM_PARTICLE_TYPES] = 1.0
        root_attr[:, NUM_PARTICLE_TYPES + 1:] = 0.0
        return torch.cat([attr, root_attr]), torch.cat([state, root_state])

    def rigid_velocity(self, params: torch.Tensor, position: torch.Tensor, bodies: RigidBodies) -> torch.Tensor:
        """Velocities [K, D] of the rigid leaves under their body's predicted motion about its centroid:
        v = (R - I)(p - c) + t (their `DPINet.forward`, dt = 1). Ours: t is a velocity in the dataset's
        velocity units (theirs: scaled by the position std)."""
        rotation = rotation_matrices(params[:, :params.shape[1] - self.dim])
        translation = self.denormalise_velocity(params[:, params.shape[1] - self.dim:])
        arm = position - segment_mean(position, bodies.body, bodies.count)[bodies.body]
        return torch.einsum("kij,kj->ki", rotation[bodies.body], arm) - arm + translation[bodies.body]

    def forward(self, window: torch.Tensor, particle_type: torch.Tensor, batch: torch.Tensor | None = None,
                context: torch.Tensor | None = None, edge_index: torch.Tensor | None = None,
                bounds: torch.Tensor | None = None, rest_shape: torch.Tensor | None = None, *,
                rigid_body: torch.Tensor | None = None, precision: str = "fp32") -> torch.Tensor:
        """Normalised next velocities [N, D]; arguments as `predict_next_position`'s. The network runs under
        `precision`, the rigid motion in the window's dtype."""
        if context is not None:
            raise ValueError("DPI-Net takes no global context; this dataset has one")
        rest_shape = window[:, 0] if rest_shape is None else rest_shape
        graph = self.graph(window, particle_type, batch, edge_index, rest_shape, rigid_body)
        attr, state = self.node_inputs(window, particle_type, graph)
        with autocast(window.device, precision):
            particle, rigid = self.network(attr, state, graph)
        velocity = particle.to(window.dtype)
        if rigid is not None and self.config.rigid_head == "transform":
            leaves = graph.bodies.leaves
            moved = self.rigid_velocity(rigid.to(window.dtype), window[leaves, -1], graph.bodies)
            velocity = velocity.index_copy(0, leaves, self.normalise_velocity(moved))
        return velocity

    def predict_next_position(self, window: torch.Tensor, particle_type: torch.Tensor,
                              batch: torch.Tensor | None = None, context: torch.Tensor | None = None,
                              edge_index: torch.Tensor | None = None, bounds: torch.Tensor | None = None,
                              precision: str = "fp32", rest_shape: torch.Tensor | None = None, *,
                              rigid_body: torch.Tensor | None = None) -> torch.Tensor:
        """Next positions [N, D] (callers put kinematic particles back from the data).

        rest_shape [N, D]: the rigid particles' rest positions (None: the window's first frame). With
        `config.project_rigid` each body's prediction is replaced by its rigid_projection onto the rest
        shape. `bounds` is accepted for the simulator interface and unused: DPI-Net has no wall features,
        it knows the walls from absolute positions normalised over the training data's box.
        """
        rest_shape = window[:, 0] if rest_shape is None else rest_shape
        normalised = self(window, particle_type, batch, context, edge_index, bounds, rest_shape,
                          rigid_body=rigid_body, precision=precision)
        position = window[:, -1] + self.denormalise_velocity(normalised)
        if self.config.project_rigid:
            position = self.project_rigid_bodies(position, rest_shape, rigid_bodies(particle_type, batch, rigid_body))
        return position

    @staticmethod
    def project_rigid_bodies(position: torch.Tensor, rest_shape: torch.Tensor, bodies: RigidBodies) -> torch.Tensor:
        position = position.clone()
        for b in range(bodies.count):
            members = bodies.leaves[bodies.body == b]
            position[members] = rigid_projection(position[members], rest_shape[members].to(position.dtype))
        return position

    def training_loss(self, window: torch.Tensor, target: torch.Tensor, particle_type: torch.Tensor,
                      batch: torch.Tensor | None, position_noise: torch.Tensor, *,
                      rigid_body: torch.Tensor | None = None, precision: str = "fp32") -> torch.Tensor:
        """Their loss (train.py): the MSE, over dims and non-kinematic particles, between predicted and true
        normalised next velocities. No rigid projection inside (theirs has none: the transform head is
        rigid already). `position_noise` [N, W, D] corrupts the window as for the GNS (zeros: theirs)."""
        noisy, target_next = noisy_training_pair(window, target, position_noise)
        truth = self.normalise_velocity(target_next - noisy[:, -1])
        predicted = self(noisy, particle_type, batch, rigid_body=rigid_body, precision=precision).float()
        moving = (particle_type != KINEMATIC_PARTICLE_TYPE).to(predicted.dtype)
        per_particle = (predicted - truth.float()).square().mean(dim=1)
        return (per_particle * moving).sum() / moving.sum().clamp(min=1)
