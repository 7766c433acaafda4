"""The graph view of a map (paper Sec. IV-B, Fig. 3): regions, their adjacency, the abstract state.

Everything is derived from the layout's region grid; nothing about a particular map is hard-coded.
The arrays are numpy (static), the functions on states are pure and jit-able.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxusar.envs.layout import Layout


class RegionGraph:
    """Regions of a map as a graph.

    Attributes:
      cell_region:   int32[H, W], region of each cell (-1 on wall and obstacle cells).
      names, kinds:  tuple[str] per region (``kind`` is ``room`` or ``hall``).
      adjacency:     bool[R, R], regions that share an edge between two open cells (no self loops).
      victim_region: int32[n_victims], region of each victim's cell.
      rooms:         tuple[int], indices of the ``room`` regions, in region order.
    """

    def __init__(self, layout: Layout):
        self.cell_region = layout.region
        self.names = layout.region_names
        self.kinds = layout.region_kinds
        self.n_regions = len(self.names)
        adj = np.zeros((self.n_regions, self.n_regions), bool)
        reg = self.cell_region
        for a, b in ((reg[:, :-1], reg[:, 1:]), (reg[:-1, :], reg[1:, :])):
            both = (a >= 0) & (b >= 0) & (a != b)
            adj[a[both], b[both]] = True
            adj[b[both], a[both]] = True
        self.adjacency = adj
        self.victim_region = reg[tuple(layout.victim_pos.T)].astype(np.int32)
        self.rooms = tuple(i for i, k in enumerate(self.kinds) if k == "room")

    def index(self, name: str) -> int:
        if name not in self.names:
            raise KeyError(f"no region {name!r}; regions: {self.names}")
        return self.names.index(name)

    def region_of(self, pos: jax.Array) -> jax.Array:
        """int32[...]: region of each (row, col) in ``pos`` int32[..., 2]."""
        return jnp.asarray(self.cell_region)[pos[..., 0], pos[..., 1]]

    def abstract_state(self, state) -> tuple[jax.Array, jax.Array]:
        """The coordinator's view (Sec. IV-C): (region of each agent int32[n_agents], triaged bool[n_victims])."""
        return self.region_of(state.agent_pos), state.triaged

    def edges(self) -> list[tuple[str, str]]:
        i, j = np.nonzero(np.triu(self.adjacency))
        return [(self.names[a], self.names[b]) for a, b in zip(i, j)]
