"""Environments: ASCII layouts, the pure-JAX USAR grid world, its observations, graph view, rendering.

``make(name, **overrides)`` is the registry: ``name`` is a shipped map (see ``available_layouts()``)
or a path to a ``.txt`` layout with its ``.regions.txt`` beside it.
"""

from jaxusar.envs.graph import RegionGraph
from jaxusar.envs.layout import (
    CRITICAL, ENGINEER, HEADER_KEYS, MEDIC, OBSERVATIONS, REGULAR, Layout, LayoutError, available_layouts,
    load_layout, parse_layout,
)
from jaxusar.envs.usar import (
    ACTION_NAMES, DIRECTION_NAMES, EAST, FORWARD, N_ACTIONS, NORTH, SOUTH, TRIAGE, TURN_LEFT,
    TURN_RIGHT, WEST, EnvState, USAREnv,
)

# Episode parameters, then the map settings a layout's header may also set (an override wins), then the
# observation's encoding (``USAREnv``: one-hot float32 blocks, or one integer code per block).
OVERRIDES = ("horizon", "triage_reward", "step_penalty", "start_dir") + tuple(HEADER_KEYS) + ("encoding",)


def make(name: str | Layout, **overrides) -> USAREnv:
    """Build an env: ``make("two_rooms", horizon=300)``, ``make("minimap", observation="view")``.
    Unknown names or overrides, and bad values, are errors naming them."""
    unknown = sorted(set(overrides) - set(OVERRIDES))
    if unknown:
        raise TypeError(f"unknown env override(s) {unknown}; allowed: {list(OVERRIDES)}")
    layout = name if isinstance(name, Layout) else load_layout(name)
    return USAREnv(layout, **overrides)


__all__ = [
    "make", "available_layouts", "load_layout", "parse_layout", "Layout", "LayoutError", "RegionGraph",
    "USAREnv", "EnvState", "OVERRIDES", "HEADER_KEYS", "OBSERVATIONS", "ACTION_NAMES", "DIRECTION_NAMES",
    "N_ACTIONS", "EAST", "SOUTH", "WEST", "NORTH", "FORWARD", "TURN_LEFT", "TURN_RIGHT", "TRIAGE",
    "MEDIC", "ENGINEER", "REGULAR", "CRITICAL",
]
