"""Continuous Convolution (CConv), the baseline of the GNS paper's Sec. 5.5 / App. D, in pure PyTorch.

CConv is Ummenhofer et al., "Lagrangian Fluid Simulation with Continuous Convolutions" (ICLR 2020). The numbers
and choices here follow the authors' code, isl-org/DeepLagrangianFluids: models/default_torch.py (network),
scripts/train_network_torch.py (loss, two unrolled steps, schedule), and the Open3D layer it calls
(open3d.ml.torch.layers.ContinuousConv; reference maths in Open3D's python/test/ml_ops/cconv_python.py).

One continuous convolution at a query point x over the sources x_j closer than the radius r:

    out(x) = sum_j  a(|x_j - x| / r) * f_j @ g(Lambda((x_j - x) / r))  (+ bias)

  Lambda  maps the unit ball onto the cube [-1, 1]^D preserving volume: in 3D Griepentrog et al.'s map, ball ->
          cylinder -> cube (Open3D's 'ball_to_cube_volume_preserving'); in 2D the inverse of Shirley & Chiu's
          concentric square -> disk map, which is equal-area and is exactly the cylinder -> cube step of the 3D
          map applied to a cross-section;
  g       a grid of K^D matrices [C_in, C_out] (K = 4), the outer nodes on the cube's faces (align_corners), read
          by bilinear / trilinear interpolation with clamping;
  a       the poly6 window clamp((1 - q^2)^3, 0, 1);
  no normalisation by the neighbour count (the authors set normalize=False).

The interpolation weights depend on positions only; they are computed once per step and shared by every layer,
as one sparse matrix (the edges' 2^D filter lookups) and its transpose for the backward pass. As in Open3D
(whose op has no gradient with respect to positions) the geometry is not differentiated.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import warnings
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from gns_bench.config import CConvConfig, ConfigError
from gns_bench.data.format import KINEMATIC_PARTICLE_TYPE, Metadata
from gns_bench.model.features import wall_distances
from gns_bench.model.neighbours import radius_graph
from gns_bench.model.precision import autocast

CONTEXT_STD_FLOOR = 1e-8


def learning_rate(config: CConvConfig, step: int, steps: int) -> float:
    """The authors' piecewise-constant schedule (train_network_torch.py:67-90), its boundaries fractions of the
    run (`steps`): base lr times the factor of the last boundary that `step` has passed."""
    passed = sum(step > fraction * steps for fraction in config.lr_boundaries)
    return config.learning_rate * config.lr_factors[passed]


# ----------------------------------------------------------------------------------------------
# The convolution
# ----------------------------------------------------------------------------------------------

def _disk_to_square(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit disk -> [-1, 1]^2, the inverse of Shirley & Chiu's concentric map (equal-area, area ratio 4 / pi)."""
    r = torch.sqrt(x * x + y * y)
    x_wide = y.abs() <= x.abs()  # the wedge around the x axis
    safe_x = torch.where(x == 0, torch.ones_like(x), x)
    safe_y = torch.where(y == 0, torch.ones_like(y), y)
    angle_x = (4 / math.pi) * torch.atan(y / safe_x)  # in [-1, 1] inside the wedge
    angle_y = (4 / math.pi) * torch.atan(x / safe_y)
    u = torch.where(x_wide, torch.sign(x) * r, torch.sign(y) * r * angle_y)
    v = torch.where(x_wide, torch.sign(x) * r * angle_x, torch.sign(y) * r)
    return u, v


def _ball_to_cylinder(p: torch.Tensor) -> torch.Tensor:
    """Unit ball -> cylinder (unit disk x [-1, 1], axis the last coordinate), volume preserving (Griepentrog et
    al. 2008): points near the axis (5/4 z^2 > x^2 + y^2) go to the caps, the others to the side."""
    x, y, z = p.unbind(-1)
    t = p.norm(dim=-1)
    rho = torch.sqrt(x * x + y * y)
    tiny = torch.finfo(p.dtype).tiny
    cap = 1.25 * z * z > rho * rho
    s = torch.where(cap, torch.sqrt(3 * t / (t + z.abs()).clamp_min(tiny)), t / rho.clamp_min(tiny))
    height = torch.where(cap, torch.sign(z) * t, 1.5 * z)
    return torch.stack([s * x, s * y, height], dim=-1)


def ball_to_cube(p: torch.Tensor, mapping: str = "ball_to_cube_volume_preserving") -> torch.Tensor:
    """Points [..., D] of the unit ball -> the cube [-1, 1]^D (D = 2 or 3)."""
    if mapping == "ball_to_cube_radial":  # stretch each ray so the sphere lands on the cube
        inf_norm = p.abs().amax(dim=-1, keepdim=True)
        return p * p.norm(dim=-1, keepdim=True) / inf_norm.clamp_min(torch.finfo(p.dtype).tiny)
    if mapping != "ball_to_cube_volume_preserving":
        raise ValueError(f"unknown coordinate mapping {mapping!r}")
    if p.shape[-1] == 2:
        return torch.stack(_disk_to_square(p[..., 0], p[..., 1]), dim=-1)
    if p.shape[-1] == 3:
        c = _ball_to_cylinder(p)
        u, v = _disk_to_square(c[..., 0], c[..., 1])
        return torch.stack([u, v, c[..., 2]], dim=-1)
    raise ValueError(f"ball_to_cube needs D = 2 or 3, got {p.shape[-1]}")


def poly6_window(q2: torch.Tensor) -> torch.Tensor:
    """The window a(q) of squared normalised distances q^2 = |x_j - x|^2 / r^2 (default_torch.py:37-38)."""
    return torch.clamp((1 - q2) ** 3, 0, 1)


class ConvGeometry(NamedTuple):
    """Where each edge reads the filter: the 2^D grid nodes around its mapped position and their weights
    (interpolation weight times window), for queries numbered 0..num_queries-1; and the same lookups as one sparse
    matrix, `lookup` [num_queries x K^D, num_sources] (row: query x K^D + node), with its transpose."""

    senders: torch.Tensor  # [E] index into the sources
    receivers: torch.Tensor  # [E] index into the queries
    nodes: torch.Tensor  # [E, 2^D] flat filter index, x fastest (the filter tensor is [.., z, y, x, C_in, C_out])
    weights: torch.Tensor  # [E, 2^D]
    window: torch.Tensor  # [E] the window values alone (for normalize)
    num_queries: int
    lookup: torch.Tensor  # sparse CSR [num_queries * K^D, num_sources]: cell sums = lookup @ source features
    lookup_t: torch.Tensor  # sparse CSR, its transpose (the gradient with respect to the source features)


def _csr(rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """A CSR matrix from COO entries (repeated (row, col) pairs add up, as in a scatter)."""
    order = torch.argsort(rows)
    crow = torch.zeros(shape[0] + 1, dtype=torch.long, device=rows.device)
    crow[1:] = torch.bincount(rows, minlength=shape[0]).cumsum(0)
    with warnings.catch_warnings():  # torch calls its sparse CSR support "beta" at every construction
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(crow, cols[order], values[order], shape, check_invariants=False)


def _lookup_matrices(nodes: torch.Tensor, weights: torch.Tensor, senders: torch.Tensor,
                     receivers: torch.Tensor, num_queries: int, num_sources: int,
                     cells: int) -> tuple[torch.Tensor, torch.Tensor]:
    rows = (receivers[:, None] * cells + nodes).reshape(-1)
    cols = senders.repeat_interleave(nodes.shape[1])
    values = weights.reshape(-1)
    return (_csr(rows, cols, values, (num_queries * cells, num_sources)),
            _csr(cols, rows, values, (num_sources, num_queries * cells)))


class _LookupMatmul(torch.autograd.Function):
    """lookup @ features, differentiated with respect to the features only (the geometry is constant), by the
    stored transpose. Runs in the matrices' dtype, outside autocast: it is the accumulation of the scatter."""

    @staticmethod
    def forward(ctx, lookup: torch.Tensor, lookup_t: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        ctx.lookup_t = lookup_t
        with torch.autocast(features.device.type, enabled=False):
            return lookup @ features

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[None, None, torch.Tensor]:
        with torch.autocast(grad.device.type, enabled=False):
            return None, None, ctx.lookup_t @ grad.to(ctx.lookup_t.dtype)


@torch.compiler.disable  # sparse CSR tensors are not traced by torch.compile: the network compiles around this
def _cell_sums(geometry: ConvGeometry, features: torch.Tensor) -> torch.Tensor:
    return _LookupMatmul.apply(geometry.lookup, geometry.lookup_t, features.to(geometry.weights.dtype))


def cconv_geometry(source_position: torch.Tensor, query_position: torch.Tensor, senders: torch.Tensor,
                   receivers: torch.Tensor, radius: float, filter_resolution: int = 4,
                   coordinate_mapping: str = "ball_to_cube_volume_preserving",
                   window: str = "poly6") -> ConvGeometry:
    """The filter lookups of the edges sender -> receiver (sources [M, D], queries [N, D])."""
    k, dim = filter_resolution, source_position.shape[1]
    rel = (source_position.detach().index_select(0, senders)
           - query_position.detach().index_select(0, receivers)) / radius
    q2 = rel.square().sum(dim=1)
    window_value = poly6_window(q2) if window == "poly6" else torch.ones_like(q2)
    grid = (ball_to_cube(rel, coordinate_mapping) + 1) * (0.5 * (k - 1))  # in [0, K-1] (align_corners)
    lower = torch.floor(grid).clamp(0, k - 1)
    frac = (grid - lower).clamp(0, 1)
    lower = lower.long()
    upper = (lower + 1).clamp(max=k - 1)
    nodes, weights = [], []
    for corner in itertools.product((0, 1), repeat=dim):
        index = torch.zeros_like(senders)
        weight = window_value
        for d, bit in enumerate(corner):
            index = index + (upper[:, d] if bit else lower[:, d]) * k**d
            weight = weight * (frac[:, d] if bit else 1 - frac[:, d])
        nodes.append(index)
        weights.append(weight)
    nodes, weights = torch.stack(nodes, dim=1), torch.stack(weights, dim=1)
    num_queries = query_position.shape[0]
    lookup, lookup_t = _lookup_matrices(nodes, weights, senders, receivers, num_queries, source_position.shape[0],
                                        k**dim)
    return ConvGeometry(senders, receivers, nodes, weights, window_value, num_queries, lookup, lookup_t)


def apply_cconv(features: torch.Tensor, geometry: ConvGeometry, kernel: torch.Tensor,
                bias: torch.Tensor | None = None, normalize: bool = False) -> torch.Tensor:
    """Output features [N, C_out] from source features [M, C_in] and a filter [K, .., K, C_in, C_out].

    Each source's weighted features are summed into its receiver's filter cells (the sparse `lookup` matrix times
    the features), then one matmul with the flattened filter sums over cells and channels. Accumulation runs in
    the geometry's dtype (fp32 under bf16 autocast); the matmul follows autocast. The sparse product replaced 2^D
    scatters (index_add) of per-edge weighted copies of the features: a SAND training step (cpu tier, batch 2,
    bf16) went from 3.38 to 6.68 steps/s, the mean over the same 95 steps (AMD EPYC family 25, 2 threads)."""
    c_in, c_out = kernel.shape[-2:]
    cells = kernel[..., 0, 0].numel()
    n = geometry.num_queries
    cell_sums = _cell_sums(geometry, features)
    out = cell_sums.reshape(n, cells * c_in) @ kernel.reshape(cells * c_in, c_out)
    if normalize:  # Open3D's normalize: divide by the sum of the window values (the count without a window)
        total = geometry.window.new_zeros(n).index_add(0, geometry.receivers, geometry.window)
        out = out / torch.where(total > 0, total, torch.ones_like(total)).unsqueeze(1).to(out.dtype)
    return out if bias is None else out + bias


def continuous_conv(features: torch.Tensor, source_position: torch.Tensor, query_position: torch.Tensor,
                    edge_index: torch.Tensor, radius: float, kernel: torch.Tensor, bias: torch.Tensor | None = None,
                    coordinate_mapping: str = "ball_to_cube_volume_preserving", window: str = "poly6",
                    normalize: bool = False) -> torch.Tensor:
    """One continuous convolution over edges [2, E] (sender into the sources, receiver into the queries)."""
    geometry = cconv_geometry(source_position, query_position, edge_index[0], edge_index[1], radius,
                              kernel.shape[0], coordinate_mapping, window)
    return apply_cconv(features, geometry, kernel, bias, normalize)


class ContinuousConv(nn.Module):
    """A continuous convolution layer: filter [K]*D + [C_in, C_out] initialised U(-0.05, 0.05), zero bias
    (Open3D's defaults, which the authors keep)."""

    def __init__(self, in_channels: int, out_channels: int, dim: int, filter_resolution: int = 4,
                 bias: bool = True, normalize: bool = False):
        super().__init__()
        self.normalize = normalize
        self.kernel = nn.Parameter(torch.empty(*[filter_resolution] * dim, in_channels, out_channels))
        nn.init.uniform_(self.kernel, -0.05, 0.05)
        self.bias = nn.Parameter(torch.zeros(out_channels)) if bias else None

    def forward(self, features: torch.Tensor, geometry: ConvGeometry) -> torch.Tensor:
        return apply_cconv(features, geometry, self.kernel, self.bias, self.normalize)


# ----------------------------------------------------------------------------------------------
# The network and the simulator
# ----------------------------------------------------------------------------------------------

def _dense(in_features: int, out_features: int) -> nn.Linear:
    layer = nn.Linear(in_features, out_features)
    nn.init.xavier_uniform_(layer.weight)
    nn.init.zeros_(layer.bias)
    return layer


class CConvNetwork(nn.Module):
    """The authors' default network (default_torch.py:60-160): layer 0 concatenates a convolution over obstacle
    neighbours, one over fluid neighbours and a dense layer on the particle itself; every further layer is
    conv + dense on ReLU of the previous output, plus the previous output where the widths agree."""

    def __init__(self, dim: int, fluid_in: int, obstacle_in: int, channels: list[int], filter_resolution: int,
                 normalize: bool):
        super().__init__()

        def conv(i: int, o: int) -> ContinuousConv:
            return ContinuousConv(i, o, dim, filter_resolution, normalize=normalize)

        c0 = channels[0]
        self.conv0_fluid = conv(fluid_in, c0)
        self.conv0_obstacle = conv(obstacle_in, c0)
        self.dense0_fluid = _dense(fluid_in, c0)
        widths = [3 * c0, *channels[1:], dim]
        self.convs = nn.ModuleList(conv(i, o) for i, o in itertools.pairwise(widths))
        self.denses = nn.ModuleList(_dense(i, o) for i, o in itertools.pairwise(widths))

    def forward(self, fluid_features: torch.Tensor, obstacle_features: torch.Tensor, fluid: ConvGeometry,
                obstacle: ConvGeometry) -> torch.Tensor:
        h = torch.cat([self.conv0_obstacle(obstacle_features, obstacle), self.conv0_fluid(fluid_features, fluid),
                       self.dense0_fluid(fluid_features)], dim=1)
        for conv, dense in zip(self.convs, self.denses, strict=True):
            x = F.relu(h)
            out = conv(x, fluid) + dense(x)
            h = out + h if out.shape[-1] == h.shape[-1] else out
        return h


class StepOutput(NamedTuple):
    position: torch.Tensor  # [N, D] next positions; kinematic particles: constant-velocity extrapolation
    fluid_neighbours: torch.Tensor  # [N] fluid neighbours within the radius at x* (0 for kinematic particles)


class CConvSimulator(nn.Module):
    """CConv as a learned simulator: x* from gravity and the last velocity, then x_new = x* + network(x*).

    Fluid means every non-kinematic particle. Kinematic particles (type 3) are only sources, of the obstacle
    convolution (their feature a constant 1: ours carry no normals, the authors' obstacle feature); they are never
    queries nor in the loss, and at the step they sit at their constant-velocity extrapolation x_t + v_t (exact
    for static and uniformly moving boundaries; callers overwrite them with the data afterwards)."""

    architecture = "cconv"
    uses_edges = True
    self_edges = False  # the authors' search leaves a particle out of its own neighbourhood

    def __init__(self, config: CConvConfig, metadata: Metadata, connectivity_radius: float,
                 input_sequence_length: int = 6, wall_range: float = 1.0):
        """`connectivity_radius`: the resolved `model.connectivity_radius` (the dataset's R unless set), the
        convolution's radius unless `cconv.radius` sets its own. `wall_range`: `model.wall_range`, how far the
        wall distances reach in multiples of that radius, as the GNS's (the release's 1 by default)."""
        super().__init__()
        # Rollouts start after this many ground-truth frames, as the GNS's do, so both are scored on the same
        # steps; CConv itself reads only the last two (its velocity).
        self.input_sequence_length = input_sequence_length
        gravity = config.gravity if config.gravity is not None else metadata.gravity
        if gravity is None:
            raise ConfigError("cconv.gravity: the dataset's metadata.json has no 'gravity'; set it in the config")
        # Resolve every dataset-dependent default here, so the stored (and logged) config holds the numbers.
        config = dataclasses.replace(
            config, radius=float(connectivity_radius if config.radius is None else config.radius),
            gravity=list(gravity),
            wall_features=bool(metadata.walls if config.wall_features is None else config.wall_features))
        config.validate()
        if len(config.gravity) != metadata.dim:
            raise ConfigError(f"cconv.gravity: expected {metadata.dim} numbers, got {config.gravity}")
        self.config = config
        self.dim = metadata.dim
        self.radius = config.radius
        self.wall_range = float(wall_range)
        self.length_scale = config.reference_radius / config.radius  # reference length units per dataset unit
        self.register_buffer("bounds", torch.tensor(metadata.bounds, dtype=torch.float32))
        self.register_buffer("gravity", torch.tensor(config.gravity, dtype=torch.float32))
        self.context_size = metadata.context_size
        if self.context_size:
            self.register_buffer("context_mean", torch.tensor(metadata.context_mean, dtype=torch.float32))
            std = [max(s, CONTEXT_STD_FLOOR) for s in metadata.context_std]
            self.register_buffer("context_std", torch.tensor(std, dtype=torch.float32))
        # Fluid features: a constant 1 and the velocity (default_torch.py:122), then the authors' other_feats slot:
        # the wall distances and the normalised global context.
        fluid_in = 1 + self.dim + (2 * self.dim if config.wall_features else 0) + self.context_size
        self.network = CConvNetwork(self.dim, fluid_in, 1, config.layer_channels, config.filter_resolution,
                                    config.normalize)

    @property
    def neighbour_backend(self) -> str:
        return self.config.neighbour_backend

    def build_graph(self, positions: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        return radius_graph(positions, self.radius, batch, backend=self.config.neighbour_backend, self_edges=False)

    def _geometry(self, source: torch.Tensor, query: torch.Tensor, senders: torch.Tensor,
                  receivers: torch.Tensor) -> ConvGeometry:
        c = self.config
        return cconv_geometry(source, query, senders, receivers, self.radius, c.filter_resolution,
                              c.coordinate_mapping, c.window)

    def step(self, window: torch.Tensor, particle_type: torch.Tensor, batch: torch.Tensor | None = None,
             context: torch.Tensor | None = None, bounds: torch.Tensor | None = None,
             precision: str = "fp32") -> StepOutput:
        """One step from the window's last two positions (dt = 1 stored frame)."""
        c = self.config
        n = window.shape[0]
        kinematic = particle_type == KINEMATIC_PARTICLE_TYPE
        position, velocity = window[:, -1], window[:, -1] - window[:, -2]
        gravity = self.gravity.to(window.dtype)
        velocity_star = velocity + gravity
        if c.integrator == "euler":
            position_star = position + velocity_star
        else:
            position_star = position + 0.5 * (velocity + velocity_star)
        position_star = torch.where(kinematic[:, None], position + velocity, position_star)

        # Neighbours at x* (as the authors' network searches them), whatever edges the caller found at x_t.
        senders, receivers = self.build_graph(position_star, batch)
        fluid_index = torch.nonzero(~kinematic).squeeze(1)
        local = torch.full((n,), -1, dtype=torch.long, device=window.device)
        local[fluid_index] = torch.arange(fluid_index.shape[0], device=window.device)
        into_fluid = ~kinematic[receivers]
        from_fluid = into_fluid & ~kinematic[senders]
        from_obstacle = into_fluid & kinematic[senders]
        fluid_star = position_star.index_select(0, fluid_index)
        fluid_geometry = self._geometry(fluid_star, fluid_star, local[senders[from_fluid]],
                                        local[receivers[from_fluid]])
        obstacle_geometry = self._geometry(position_star, fluid_star, senders[from_obstacle],
                                           local[receivers[from_obstacle]])

        parts = [torch.ones_like(fluid_star[:, :1]),
                 velocity_star.index_select(0, fluid_index) * (self.length_scale / c.reference_dt)]
        if c.wall_features:  # App. B.2's clipped distances to the bounds, at x*
            bounds = (self.bounds if bounds is None else bounds).to(window.dtype)
            parts.append(wall_distances(fluid_star, bounds, self.radius, self.wall_range))
        if self.context_size:
            if context is None:
                raise ValueError("this simulator was built for a dataset with a global context; pass context")
            graph = torch.zeros(n, dtype=torch.long, device=window.device) if batch is None else batch
            normalised = (context.to(window.dtype) - self.context_mean) / self.context_std
            parts.append(normalised.index_select(0, graph.index_select(0, fluid_index)))
        obstacle_features = torch.ones_like(position_star[:, :1])
        with autocast(window.device, precision):
            out = self.network(torch.cat(parts, dim=1), obstacle_features, fluid_geometry, obstacle_geometry)
        correction = out.to(window.dtype) * (c.correction_scale / self.length_scale)
        next_position = position_star.index_add(0, fluid_index, correction)
        counts = torch.zeros(fluid_index.shape[0], dtype=window.dtype, device=window.device)
        counts = counts.index_add(0, fluid_geometry.receivers, torch.ones_like(fluid_geometry.window))
        neighbours = torch.zeros(n, dtype=window.dtype, device=window.device).index_add(0, fluid_index, counts)
        return StepOutput(next_position, neighbours)

    def predict_next_position(self, window: torch.Tensor, particle_type: torch.Tensor,
                              batch: torch.Tensor | None = None, context: torch.Tensor | None = None,
                              edge_index: torch.Tensor | None = None, bounds: torch.Tensor | None = None,
                              precision: str = "fp32") -> torch.Tensor:
        """Next positions [N, D] from a window [N, W >= 2, D]. `edge_index` (edges at the last positions) is
        ignored: CConv searches its neighbours at x*. The network runs under `precision` (autocast for "bf16"),
        the integration in the window's dtype."""
        if window.shape[1] < 2:
            raise ValueError(f"CConv needs a window of at least 2 positions, got {window.shape[1]}")
        return self.step(window, particle_type, batch, context, bounds, precision).position

    def unrolled_loss(self, window: torch.Tensor, particle_type: torch.Tensor, batch: torch.Tensor | None = None,
                      context: torch.Tensor | None = None, bounds: torch.Tensor | None = None,
                      precision: str = "fp32", position_noise: torch.Tensor | None = None,
                      position_correction: float = 0.0) -> torch.Tensor:
        """The authors' loss over S = unrolled_steps predicted steps from the first W frames of window [N, W+S, D]
        (train_network_torch.py:114-145): predictions are fed back (kinematic particles from the data); step s
        costs the mean over fluid particles of exp(-neighbour_scale * n_i) |x_pred - x_true|^gamma, per scene,
        averaged over scenes, then over steps, times loss_scale.

        `position_noise` [N, W, D] (the GNS's random-walk noise, `model.noise`): its authors train without it,
        and the paper swept CConv's training noise (Sec. 5.5, App. D.1). It corrupts the W input frames, and
        every target moves by (1 - position_correction) times the last frame's noise, as the GNS's target does
        (`noisy_training_pair`): with 0 the model restores the true velocities and keeps the offset."""
        c = self.config
        steps = c.unrolled_steps
        w = window.shape[1] - steps
        if w < 2:
            raise ValueError(f"window of {window.shape[1]} frames: need >= 2 inputs + {steps} unrolled targets")
        kinematic = particle_type == KINEMATIC_PARTICLE_TYPE
        fluid_index = torch.nonzero(~kinematic).squeeze(1)
        if fluid_index.numel() == 0:
            raise ValueError("unrolled_loss needs at least one non-kinematic particle")
        graph = torch.zeros(particle_type.shape[0], dtype=torch.long, device=window.device) if batch is None else batch
        graph = graph.index_select(0, fluid_index)
        num_graphs = int(graph.max()) + 1
        per_graph = torch.zeros(num_graphs, dtype=window.dtype, device=window.device)
        count = per_graph.index_add(0, graph, torch.ones_like(graph, dtype=window.dtype))
        has_fluid = count > 0
        history, offset = window[:, :w], 0.0
        if position_noise is not None:
            if position_noise.shape != history.shape:
                raise ValueError(f"position_noise of shape {tuple(position_noise.shape)}: the {w} input frames "
                                 f"are {tuple(history.shape)}")
            history = history + position_noise
            offset = (1.0 - position_correction) * position_noise[:, -1]
        total = window.new_zeros(())
        for s in range(steps):
            out = self.step(history, particle_type, batch, context, bounds, precision)
            target = window[:, w + s] + offset
            error = (out.position - target).index_select(0, fluid_index) * self.length_scale
            distance = (error.square().sum(dim=1) + c.distance_epsilon) ** (c.gamma / 2)
            importance = torch.exp(-c.neighbour_scale * out.fluid_neighbours.index_select(0, fluid_index))
            sums = per_graph.index_add(0, graph, importance * distance)
            total = total + (sums[has_fluid] / count[has_fluid]).mean()
            fed_back = torch.where(kinematic[:, None], target, out.position)
            history = torch.cat([history[:, 1:], fed_back[:, None]], dim=1)
        return c.loss_scale * total / steps
