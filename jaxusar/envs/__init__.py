"""Environments: ASCII layouts, the pure-JAX USAR grid world, its graph view, rendering.

``make(name, **overrides)`` is the registry: ``name`` is a shipped map (see ``available_layouts()``)
or a path to a ``.txt`` layout with its ``.regions.txt`` beside it.
"""

from jaxusar.envs.graph import RegionGraph
from jaxusar.envs.layout import Layout, LayoutError, available_layouts, load_layout, parse_layout
from jaxusar.envs.usar import (
    ACTION_NAMES, DIRECTION_NAMES, EAST, FORWARD, N_ACTIONS, NORTH, SOUTH, TRIAGE, TURN_LEFT,
    TURN_RIGHT, WEST, EnvState, USAREnv,
)

OVERRIDES = ("horizon", "triage_reward", "step_penalty", "start_dir")


def make(name: str | Layout, **overrides) -> USAREnv:
    """Build an env: ``make("two_rooms", horizon=300)``. Unknown names or overrides are errors."""
    unknown = sorted(set(overrides) - set(OVERRIDES))
    if unknown:
        raise TypeError(f"unknown env override(s) {unknown}; allowed: {list(OVERRIDES)}")
    layout = name if isinstance(name, Layout) else load_layout(name)
    return USAREnv(layout, **overrides)


__all__ = [
    "make", "available_layouts", "load_layout", "parse_layout", "Layout", "LayoutError", "RegionGraph",
    "USAREnv", "EnvState", "OVERRIDES", "ACTION_NAMES", "DIRECTION_NAMES", "N_ACTIONS",
    "EAST", "SOUTH", "WEST", "NORTH", "FORWARD", "TURN_LEFT", "TURN_RIGHT", "TRIAGE",
]
