"""Options derived from a map's graph view (paper Sec. IV-B, Table I): nothing map-specific here.

For each room region R: NAVIGATE-TO-R (termination: the agent is in R). Its initiation set depends
on ``navigation``: ``adjacent`` (the paper, Sec. IV-B): the agent is in a region adjacent to R;
``chained``: the agent is in any other region from which R can be reached; the option then runs the
adjacent-region sub-policies along the region graph's shortest path (``next_hop``; the paper's
"chaining options", its future work); ``goal``: the same initiation set, run by one goal-conditioned
sub-policy. For each victim v, in room R: TRIAGE-v (initiation: the agent
is in R and v is not yet triaged; termination: v is triaged). On the two-rooms map this is Table I:
NAVIGATE-TO-TOP-ROOM, NAVIGATE-TO-BOTTOM-ROOM, TRIAGE-TOP-VICTIM, TRIAGE-BOTTOM-VICTIM.

Initiation and termination are pure functions of the abstract state (agent region, triaged flags),
usable inside jit.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxusar.envs.graph import RegionGraph

NAVIGATE, TRIAGE = 0, 1


@dataclasses.dataclass(frozen=True, eq=False)
class Options:
    """The option set of a map. Arrays are numpy (static), one entry per option."""

    names: tuple[str, ...]
    kind: np.ndarray      # int32[O]: NAVIGATE or TRIAGE
    region: np.ndarray    # int32[O]: the room to reach (NAVIGATE) or the victim's room (TRIAGE)
    victim: np.ndarray    # int32[O]: the victim to triage, -1 for NAVIGATE
    starts_from: np.ndarray  # bool[R, R]: NAVIGATE-TO-r may start in region q where starts_from[q, r]

    @property
    def n(self) -> int:
        return len(self.names)

    def can_initiate(self, agent_region: jax.Array, triaged: jax.Array) -> jax.Array:
        """bool[O]: options whose initiation set holds for an agent in ``agent_region``."""
        may_go = jnp.asarray(self.starts_from)[agent_region, jnp.asarray(self.region)]
        victim_open = ~triaged[jnp.maximum(jnp.asarray(self.victim), 0)]
        in_room = agent_region == jnp.asarray(self.region)
        return jnp.where(jnp.asarray(self.kind) == NAVIGATE, may_go, in_room & victim_open)

    def terminated(self, option: jax.Array, agent_region: jax.Array, triaged: jax.Array) -> jax.Array:
        """bool: option ``option`` (an index) has reached its termination condition."""
        kind, region, victim = (jnp.asarray(a)[option] for a in (self.kind, self.region, self.victim))
        return jnp.where(kind == NAVIGATE, agent_region == region, triaged[jnp.maximum(victim, 0)])


def room_label(name: str) -> str:
    return name.upper().replace("_", "-")


def next_hop(adjacency: np.ndarray) -> np.ndarray:
    """int32[R, R]: the region after q on a shortest path (fewest regions) from q to r; -1 where r == q
    or r cannot be reached. Ties go to the lowest region index, so the table is deterministic."""
    n = len(adjacency)
    hop = np.full((n, n), -1, np.int32)
    for r in range(n):  # breadth-first from the goal r: a region's hop is its first neighbour one layer closer
        dist = np.full(n, -1)
        dist[r], frontier = 0, [r]
        while frontier:
            nxt = []
            for q in frontier:
                for p in np.flatnonzero(adjacency[q]):
                    if dist[p] < 0:
                        dist[p] = dist[q] + 1
                        nxt.append(p)
            frontier = nxt
        for q in range(n):
            if q != r and dist[q] > 0:
                hop[q, r] = next(p for p in np.flatnonzero(adjacency[q]) if dist[p] == dist[q] - 1)
    return hop


NAVIGATIONS = ("adjacent", "chained", "goal")


def options_from_graph(graph: RegionGraph, navigation: str = "adjacent") -> Options:
    if navigation not in NAVIGATIONS:
        raise ValueError(f"navigation {navigation!r}: one of {NAVIGATIONS}")
    names, kind, region, victim = [], [], [], []
    for r in graph.rooms:
        names.append(f"NAVIGATE-TO-{room_label(graph.names[r])}")
        kind.append(NAVIGATE), region.append(r), victim.append(-1)
    for v, r in enumerate(graph.victim_region):
        if graph.kinds[r] != "room":
            raise ValueError(f"victim {v} lies in {graph.names[r]!r}, a {graph.kinds[r]}: triage options need a room")
        in_room = np.flatnonzero(graph.victim_region == r)
        room = graph.names[r]
        if len(in_room) == 1 and room.endswith("_room"):
            names.append(f"TRIAGE-{room_label(room[: -len('_room')])}-VICTIM")  # paper's Table I names
        else:
            names.append(f"TRIAGE-VICTIM-{v}-IN-{room_label(room)}")
        kind.append(TRIAGE), region.append(int(r)), victim.append(v)
    starts_from = graph.adjacency if navigation == "adjacent" else next_hop(graph.adjacency) >= 0
    return Options(tuple(names), np.asarray(kind, np.int32), np.asarray(region, np.int32),
                   np.asarray(victim, np.int32), starts_from)
