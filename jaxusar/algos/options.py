"""Options derived from a map's graph view (paper Sec. IV-B, Table I): nothing map-specific here.

For each room region R: NAVIGATE-TO-R (initiation: the agent is in a region adjacent to R;
termination: the agent is in R). For each victim v, in room R: TRIAGE-v (initiation: the agent is in
R and v is not yet triaged; termination: v is triaged). On the two-rooms map this is Table I:
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
    adjacency: np.ndarray  # bool[R, R] of the graph

    @property
    def n(self) -> int:
        return len(self.names)

    def can_initiate(self, agent_region: jax.Array, triaged: jax.Array) -> jax.Array:
        """bool[O]: options whose initiation set holds for an agent in ``agent_region``."""
        adjacent = jnp.asarray(self.adjacency)[agent_region, jnp.asarray(self.region)]
        victim_open = ~triaged[jnp.maximum(jnp.asarray(self.victim), 0)]
        in_room = agent_region == jnp.asarray(self.region)
        return jnp.where(jnp.asarray(self.kind) == NAVIGATE, adjacent, in_room & victim_open)

    def terminated(self, option: jax.Array, agent_region: jax.Array, triaged: jax.Array) -> jax.Array:
        """bool: option ``option`` (an index) has reached its termination condition."""
        kind, region, victim = (jnp.asarray(a)[option] for a in (self.kind, self.region, self.victim))
        return jnp.where(kind == NAVIGATE, agent_region == region, triaged[jnp.maximum(victim, 0)])


def _room_label(name: str) -> str:
    return name.upper().replace("_", "-")


def options_from_graph(graph: RegionGraph) -> Options:
    names, kind, region, victim = [], [], [], []
    for r in graph.rooms:
        names.append(f"NAVIGATE-TO-{_room_label(graph.names[r])}")
        kind.append(NAVIGATE), region.append(r), victim.append(-1)
    for v, r in enumerate(graph.victim_region):
        if graph.kinds[r] != "room":
            raise ValueError(f"victim {v} lies in {graph.names[r]!r}, a {graph.kinds[r]}: triage options need a room")
        in_room = np.flatnonzero(graph.victim_region == r)
        room = graph.names[r]
        if len(in_room) == 1 and room.endswith("_room"):
            names.append(f"TRIAGE-{_room_label(room[: -len('_room')])}-VICTIM")  # paper's Table I names
        else:
            names.append(f"TRIAGE-VICTIM-{v}-IN-{_room_label(room)}")
        kind.append(TRIAGE), region.append(int(r)), victim.append(v)
    return Options(tuple(names), np.asarray(kind, np.int32), np.asarray(region, np.int32),
                   np.asarray(victim, np.int32), graph.adjacency)
