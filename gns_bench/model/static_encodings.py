"""The encoder's latents of particles that never move, and of the edges among them, reused across a rollout's
steps.

The GNS encoder (Sec. 3.2, App. B.2) maps each node's and each edge's features to a latent independently of
every other node and edge. A fixed boundary's particles have the same features at every step (zero velocity,
the same wall distances and type), and so do the edges among them (the same displacements), so their latents
are the same too: they are computed at the first step and reused while those features stay equal, checked
every step (a per-step global context that enters the node features refreshes them). Only the moving
particles, and the edges touching one, go through the encoders after the first step. The outputs equal a full
encoding up to the rounding of smaller matrix products.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

Encoder = Callable[[torch.Tensor], torch.Tensor]


class StaticEncodings:
    """Encoder latents of the `static` particles [N] (bool) and of the edges among them, for one rollout."""

    def __init__(self, static: torch.Tensor):
        self.static = static
        self.static_index = static.nonzero()[:, 0]
        self.moving_index = (~static).nonzero()[:, 0]
        self._nodes: tuple[torch.Tensor, torch.Tensor] | None = None  # (features, latents) of static particles
        self._edges: tuple[torch.Tensor, torch.Tensor] | None = None  # (features, latents) of static-static edges
        self.reused = 0  # steps whose static latents were reused (nodes and edges counted apart)

    def nodes(self, features: torch.Tensor, encoder: Encoder) -> torch.Tensor:
        """The node latents [N, L] of `features` [N, F]."""
        held = self._reuse(self._nodes, features, self.static_index)
        if held is None:
            latents = encoder(features)
            self._nodes = (features.index_select(0, self.static_index), latents.index_select(0, self.static_index))
            return latents
        return self._assemble(held, features, self.moving_index, self.static_index, encoder)

    def edges(self, features: torch.Tensor, edge_index: torch.Tensor, encoder: Encoder) -> torch.Tensor:
        """The edge latents [E, L] of `features` [E, F] on the edges `edge_index` [2, E]."""
        among = self.static.index_select(0, edge_index[0]) & self.static.index_select(0, edge_index[1])
        fixed, other = among.nonzero()[:, 0], (~among).nonzero()[:, 0]
        held = self._reuse(self._edges, features, fixed)
        if held is None:
            latents = encoder(features)
            self._edges = (features.index_select(0, fixed), latents.index_select(0, fixed))
            return latents
        return self._assemble(held, features, other, fixed, encoder)

    def _reuse(self, held: tuple[torch.Tensor, torch.Tensor] | None, features: torch.Tensor,
               rows: torch.Tensor) -> torch.Tensor | None:
        """The held latents when `features`' `rows` are the features they were computed from, row by row (a
        latent depends on its own row alone, so equal rows give equal latents in any order); else None."""
        if held is None or held[0].shape[0] != rows.shape[0] or held[0].dtype != features.dtype:
            return None
        if not torch.equal(features.index_select(0, rows), held[0]):
            return None
        self.reused += 1
        return held[1]

    @staticmethod
    def _assemble(held: torch.Tensor, features: torch.Tensor, fresh: torch.Tensor, kept: torch.Tensor,
                  encoder: Encoder) -> torch.Tensor:
        encoded = encoder(features.index_select(0, fresh))
        out = encoded.new_empty((features.shape[0], encoded.shape[1]))
        out.index_copy_(0, fresh, encoded)
        out.index_copy_(0, kept, held.to(encoded.dtype))
        return out
