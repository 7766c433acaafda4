"""The USAR grid world as pure, jit-able, vmap-able functions (paper Sec. IV-A; contract in DESIGN.md).

Medics move on a grid, turn, and triage victims. The map is static (numpy arrays closed over by
``jit``); the state is a small pytree, so ``jax.vmap(env.step)`` runs many worlds at once.

Step semantics (fixed contract): agents act in index order. FORWARD moves one cell into an in-bounds,
unblocked cell holding no victim (triaged or not) and no other agent (as already moved this step);
TURN_LEFT = (dir + 3) % 4, TURN_RIGHT = (dir + 1) % 4; TRIAGE triages the untriaged victim directly in
front (else a no-op). Team reward = triage_reward x newly triaged + step_penalty. ``done`` when every
victim is triaged or ``t`` reaches the horizon. ``step`` never resets: stepping a done state goes on
(``t`` keeps counting, nothing else changes but what the actions do); callers reset.

Actions outside 0..3 given from Python raise ``ValueError``. Inside ``jit`` they cannot be checked
and act as a no-op (they match no action).
"""

from __future__ import annotations

import numbers
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxusar.envs.graph import RegionGraph
from jaxusar.envs.layout import Layout

EAST, SOUTH, WEST, NORTH = 0, 1, 2, 3
DIRECTION_NAMES = ("EAST", "SOUTH", "WEST", "NORTH")
FORWARD, TURN_LEFT, TURN_RIGHT, TRIAGE = 0, 1, 2, 3
ACTION_NAMES = ("FORWARD", "TURN_LEFT", "TURN_RIGHT", "TRIAGE")
N_ACTIONS = 4
# (d_row, d_col) of one FORWARD step per direction, in Minigrid order.
DIR_DELTA = np.array([[0, 1], [1, 0], [0, -1], [-1, 0]], dtype=np.int32)


@struct.dataclass
class EnvState:
    """agent_pos int32[n_agents, 2] (row, col); agent_dir int32[n_agents]; triaged bool[n_victims]; t int32."""

    agent_pos: jax.Array
    agent_dir: jax.Array
    triaged: jax.Array
    t: jax.Array


def apply_actions(solid, victim_at, agent_pos, agent_dir, triaged, actions):
    """The step rules on plain arrays (the one implementation every env here uses).

    solid bool[H, W]: cells no agent may enter (blocked or holding a victim); victim_at int32[H, W]:
    victim index per cell, -1 elsewhere. Map arrays may be traced, so a batch of different maps or
    tasks can be vmapped. Returns (agent_pos, agent_dir, triaged, newly_triaged).
    """
    height, width = solid.shape
    n_agents, n_victims = agent_dir.shape[0], triaged.shape[0]
    pos, dirs = agent_pos, agent_dir
    newly = jnp.zeros_like(triaged)
    for i in range(n_agents):  # index order: agent i sees agents < i already moved
        a, d = actions[i], dirs[i]
        front = pos[i] + jnp.asarray(DIR_DELTA)[d]
        inside = (front[0] >= 0) & (front[0] < height) & (front[1] >= 0) & (front[1] < width)
        front = jnp.clip(front, 0, jnp.array([height - 1, width - 1]))
        others = jnp.arange(n_agents) != i
        occupied = jnp.any(others & jnp.all(pos == front, axis=-1))
        can_move = (a == FORWARD) & inside & ~solid[front[0], front[1]] & ~occupied
        pos = pos.at[i].set(jnp.where(can_move, front, pos[i]))
        turned = jnp.where(a == TURN_LEFT, (d + 3) % 4, jnp.where(a == TURN_RIGHT, (d + 1) % 4, d))
        dirs = dirs.at[i].set(turned)
        victim = jnp.where(inside, victim_at[front[0], front[1]], -1)
        hit = (a == TRIAGE) & (jnp.arange(n_victims) == victim) & ~triaged
        newly, triaged = newly | hit, triaged | hit
    return pos, dirs, triaged, newly


def _check_override(name: str, value: Any, kind: type, low=None, high=None) -> None:
    ok_type = isinstance(value, numbers.Integral) if kind is int else isinstance(value, numbers.Real)
    if isinstance(value, bool) or not ok_type:
        raise TypeError(f"override {name}={value!r}: expected {kind.__name__}, got {type(value).__name__}")
    if not np.isfinite(value) or (low is not None and value < low) or (high is not None and value > high):
        bounds = f"[{low if low is not None else '-inf'}, {high if high is not None else 'inf'}]"
        raise ValueError(f"override {name}={value!r} is out of range {bounds}")


class USAREnv:
    """A map plus its episode parameters. Build one with ``jaxusar.envs.make``.

    Attributes (all static): ``layout``, ``graph`` (the region view), ``blocked`` bool[H, W],
    ``victim_pos`` int32[n_victims, 2], ``n_agents``, ``n_victims``, ``horizon``, ``triage_reward``,
    ``step_penalty``, ``start_dir``, ``obs_dim``.

    Observation (fully observable, paper Sec. IV-A): float32[obs_dim], the concatenation over agents
    of one-hot(row, H), one-hot(col, W), one-hot(dir, 4), then the victims' triaged flags.
    On the two-rooms map that is 2 x (10 + 15 + 4) + 2 = 60 numbers, of which 8 are non-zero.
    """

    def __init__(self, layout: Layout, horizon: int = 100, triage_reward: float = 100.0,
                 step_penalty: float = 0.0, start_dir: int | str = NORTH):
        if isinstance(start_dir, str):
            if start_dir.upper() not in DIRECTION_NAMES:
                raise ValueError(f"override start_dir={start_dir!r}: expected one of {DIRECTION_NAMES} or 0..3")
            start_dir = DIRECTION_NAMES.index(start_dir.upper())
        _check_override("horizon", horizon, int, 1, 1_000_000)
        _check_override("triage_reward", triage_reward, float)
        _check_override("step_penalty", step_penalty, float)
        _check_override("start_dir", start_dir, int, 0, 3)
        self.layout = layout
        self.graph = RegionGraph(layout)
        self.horizon = int(horizon)
        self.triage_reward = float(triage_reward)
        self.step_penalty = float(step_penalty)
        self.start_dir = int(start_dir)
        self.height, self.width = layout.shape
        self.blocked = layout.blocked
        self.victim_pos = layout.victim_pos
        self.n_agents = len(layout.agent_start)
        self.n_victims = len(layout.victim_pos)
        self.obs_dim = self.n_agents * (self.height + self.width + 4) + self.n_victims
        self.obs_blocks = (self.height, self.width, 4) * self.n_agents + (1,) * self.n_victims  # one-hot widths
        # A cell an agent may not enter: blocked or holding a victim (victims never move).
        solid = self.blocked.copy()
        solid[tuple(self.victim_pos.T)] = True
        self._solid = solid
        victim_at = np.full(layout.shape, -1, np.int32)
        victim_at[tuple(self.victim_pos.T)] = np.arange(self.n_victims)
        self._victim_at = victim_at

    def __repr__(self) -> str:
        return (f"USAREnv({self.layout.name!r}, {self.height}x{self.width}, agents={self.n_agents}, "
                f"victims={self.n_victims}, horizon={self.horizon}, triage_reward={self.triage_reward}, "
                f"step_penalty={self.step_penalty}, start_dir={DIRECTION_NAMES[self.start_dir]})")

    # -- pure functions ------------------------------------------------------------------------
    def initial_state(self) -> EnvState:
        return EnvState(
            agent_pos=jnp.asarray(self.layout.agent_start, jnp.int32),
            agent_dir=jnp.full((self.n_agents,), self.start_dir, jnp.int32),
            triaged=jnp.zeros((self.n_victims,), bool),
            t=jnp.zeros((), jnp.int32),
        )

    def reset(self, key: jax.Array) -> tuple[jax.Array, EnvState]:
        """Deterministic start (the paper's fixed starts); ``key`` is taken for API uniformity."""
        del key
        state = self.initial_state()
        return self.observe(state), state

    def observe(self, state: EnvState) -> jax.Array:
        """float32[obs_dim]: per agent one-hot(row), one-hot(col), one-hot(dir); then triaged flags."""
        parts = []
        for i in range(self.n_agents):
            parts += [jax.nn.one_hot(state.agent_pos[i, 0], self.height),
                      jax.nn.one_hot(state.agent_pos[i, 1], self.width),
                      jax.nn.one_hot(state.agent_dir[i], 4)]
        parts.append(state.triaged.astype(jnp.float32))
        return jnp.concatenate(parts)

    def step(self, key: jax.Array, state: EnvState, actions: jax.Array):
        """One joint step. Returns (obs, state, reward float32, done bool, info).

        info: ``newly_triaged`` bool[n_victims]; ``terminated`` (all victims triaged);
        ``truncated`` (horizon reached with victims left).
        """
        del key
        actions = self._check_actions(actions)
        pos, dirs, triaged, newly = apply_actions(jnp.asarray(self._solid), jnp.asarray(self._victim_at),
                                                  state.agent_pos, state.agent_dir, state.triaged, actions)
        t = state.t + 1
        state = EnvState(agent_pos=pos, agent_dir=dirs, triaged=triaged, t=t)
        reward = (self.triage_reward * newly.sum() + self.step_penalty).astype(jnp.float32)
        terminated = jnp.all(triaged)
        done = terminated | (t >= self.horizon)
        info = {"newly_triaged": newly, "terminated": terminated, "truncated": done & ~terminated}
        return self.observe(state), state, reward, done, info

    # -- python-side helpers ---------------------------------------------------------------------
    def _check_actions(self, actions) -> jax.Array:
        shape = np.shape(actions)
        if shape != (self.n_agents,):
            raise ValueError(f"actions must have shape ({self.n_agents},) (one per agent), got {shape}")
        if not isinstance(actions, jax.core.Tracer):
            values = np.asarray(actions)
            if not np.issubdtype(values.dtype, np.integer):
                raise TypeError(f"actions must be integers 0..3, got dtype {values.dtype}")
            if np.any((values < 0) | (values >= N_ACTIONS)):
                raise ValueError(f"actions must be in 0..3 {ACTION_NAMES}, got {values.tolist()}")
        return jnp.asarray(actions, jnp.int32)

    def render_ascii(self, state: EnvState) -> str:
        from jaxusar.envs.render import render_ascii

        return render_ascii(self, state)
