"""Observation encodings of the USAR world: ``full`` (the state) and ``view`` (partial observability).

Both are pure functions of an ``EnvState`` built from an env's static arrays; each is a concatenation
of one-hot blocks (a block of width 1 is a flag), whose widths the env lists in ``obs_blocks`` so
that replay rows store one small integer per block (``core.replay.OneHotCodec``).

``full``, float32[obs_dim]. On a part-1 map (no rubble, engineer, critical or drawn victim, one-step
triage, no expiry) it is part 1's vector: per agent one-hot(row, H), one-hot(col, W), one-hot(dir, 4),
then the victims' triaged flags. Elsewhere these blocks follow, so that the vector determines the state:
  - a flag per rubble cell of the layout (rubble not yet cleared);
  - per drawn victim, one-hot over the ``?`` cells: the cell it was drawn on;
  - per victim needing more than one TRIAGE, one-hot(progress, its triage steps + 1);
  - per critical victim, where victims expire, a dead flag;
  - ``t`` in binary, ``horizon.bit_length()`` flags, least significant first;
  - a seen flag per open cell not seen at reset.

``view``, float32[n_agents, obs_dim]: each agent's own observation, stacked on a leading agent axis.
Victims appear only in cells the team has seen (``state.seen``), so no number in it depends on where
an unseen victim is (tested). Per agent:
  - its pose: one-hot(row, H), one-hot(col, W), one-hot(dir, 4), and a flag for the ENGINEER role;
  - an egocentric window of (2k+1) x (2k+1) cells rotated to its facing (XLand-MiniGrid, Navix): the
    window's top row lies k cells ahead, its right column k cells to the right. k = ``view_radius``
    clipped to 1..3 (2 where the map sees whole regions). Each cell is one-hot over ``CELL_CLASSES``;
  - the team's knowledge of every cell a victim may be in (fixed victim cells, then ``?`` cells, in
    reading order), one-hot over ``VICTIM_CELL_CLASSES``;
  - a flag per rubble cell of the layout (the floor plan and its rubble are known to every agent);
  - where victims need more than one TRIAGE: one-hot of the progress of the victim in front (0 where
    there is none, or it is not seen), width the largest triage steps;
  - where victims expire: ``t`` in binary, as in ``full``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# Classes of a cell in the egocentric window, in the priority they are assigned (first match wins).
CELL_CLASSES = ("wall", "agent", "rubble", "not seen", "regular victim", "critical victim",
                "triaged or dead victim", "floor")
WALL, AGENT, RUBBLE, NOT_SEEN, REGULAR_VICTIM, CRITICAL_VICTIM, DONE_VICTIM, FLOOR = range(len(CELL_CLASSES))
# What the team knows of a cell a victim may be in.
VICTIM_CELL_CLASSES = ("not seen", "no victim", "regular victim", "critical victim", "triaged", "dead")


def time_bits(t: jax.Array, n_bits: int) -> jax.Array:
    """float32[n_bits]: ``t`` in binary, least significant bit first."""
    return ((t >> jnp.arange(n_bits)) & 1).astype(jnp.float32)


def window_offsets(radius: int) -> np.ndarray:
    """int32[4, (2k+1)^2, 2]: per facing, the (d_row, d_col) of each window cell, row-major from the
    window's top-left; its top row lies ``radius`` cells ahead, its right column to the agent's right."""
    from jaxusar.envs.usar import DIR_DELTA

    span = np.arange(-radius, radius + 1)
    u, v = np.meshgrid(span, span, indexing="ij")  # u < 0: ahead; v > 0: right
    out = []
    for d in range(4):
        ahead, right = DIR_DELTA[d], DIR_DELTA[(d + 1) % 4]
        out.append((-u.ravel())[:, None] * ahead + v.ravel()[:, None] * right)
    return np.asarray(out, np.int32)


class Encoder:
    """The observation blocks of one env (static arrays and sizes), and its ``full`` and ``view`` encodings."""

    def __init__(self, env):
        self.env = env
        h, w = env.height, env.width
        layout = env.layout
        self.rubble_cells = np.argwhere(layout.rubble).astype(np.int32)
        self.staged = [k for k in range(env.n_victims) if env.needed[k] > 1]
        self.critical = np.flatnonzero(env.victim_kind == 1)
        self.time_bits = max(1, int(env.horizon).bit_length())
        open_ = ~layout.blocked
        self.unseen_at_reset = np.argwhere(open_ & ~env.seen_at_reset).astype(np.int32)
        self.victim_cells = np.concatenate([layout.victim_pos, layout.random_cells]).astype(np.int32)
        self.window = 2 if env.view_radius is None else int(np.clip(env.view_radius, 1, 3))
        self.offsets = window_offsets(self.window)
        pose = (h, w, 4)
        if env.part1:
            self.full_blocks = pose * env.n_agents + (1,) * env.n_victims
        else:
            self.full_blocks = (pose * env.n_agents + (1,) * env.n_victims + (1,) * len(self.rubble_cells)
                                + (len(layout.random_cells),) * env.n_drawn
                                + tuple(int(env.needed[k]) + 1 for k in self.staged)
                                + ((1,) * len(self.critical) if env.expires else ())
                                + (1,) * self.time_bits + (1,) * len(self.unseen_at_reset))
        self.view_blocks = (pose + (1,) + (len(CELL_CLASSES),) * len(self.offsets[0])
                            + (len(VICTIM_CELL_CLASSES),) * len(self.victim_cells) + (1,) * len(self.rubble_cells)
                            + ((int(env.needed.max()),) if self.staged else ())
                            + ((1,) * self.time_bits if env.expires else ()))

    # -- full ---------------------------------------------------------------------------------------
    def full(self, state) -> jax.Array:
        env = self.env
        parts = []
        for i in range(env.n_agents):
            parts += [jax.nn.one_hot(state.agent_pos[i, 0], env.height), jax.nn.one_hot(state.agent_pos[i, 1], env.width),
                      jax.nn.one_hot(state.agent_dir[i], 4)]
        parts.append(state.triaged.astype(jnp.float32))
        if env.part1:
            return jnp.concatenate(parts)
        if len(self.rubble_cells):
            parts.append(state.rubble[tuple(self.rubble_cells.T)].astype(jnp.float32))
        if env.n_drawn:
            cells = jnp.asarray(env.layout.random_cells)
            drawn = state.victim_pos[env.n_fixed:]
            at = jnp.all(drawn[:, None, :] == cells[None, :, :], -1)  # [n_drawn, n_cells]
            parts.append(at.astype(jnp.float32).ravel())
        for k in self.staged:
            parts.append(jax.nn.one_hot(state.progress[k], int(env.needed[k]) + 1))
        if env.expires:
            parts.append(state.dead[self.critical].astype(jnp.float32))
        parts.append(time_bits(state.t, self.time_bits))
        if len(self.unseen_at_reset):
            parts.append(state.seen[tuple(self.unseen_at_reset.T)].astype(jnp.float32))
        return jnp.concatenate(parts)

    # -- view ---------------------------------------------------------------------------------------
    def _cell_classes(self, state, victim_at) -> jax.Array:
        """int32[H, W]: the window class of every cell, as the team sees it."""
        env = self.env
        kind = jnp.asarray(env.victim_kind)
        v = jnp.maximum(victim_at, 0)
        living = jnp.where(kind[v] == 1, CRITICAL_VICTIM, REGULAR_VICTIM)
        victim = jnp.where(state.triaged[v] | state.dead[v], DONE_VICTIM, living)
        cls = jnp.where((victim_at >= 0) & state.seen, victim, FLOOR)
        cls = jnp.where(state.seen, cls, NOT_SEEN)
        cls = jnp.where(state.rubble, RUBBLE, cls)
        cls = cls.at[state.agent_pos[:, 0], state.agent_pos[:, 1]].set(AGENT)
        return jnp.where(jnp.asarray(env.blocked), WALL, cls)

    def _victim_cells(self, state, victim_at) -> jax.Array:
        """int32[n_cells]: ``VICTIM_CELL_CLASSES`` index of each cell a victim may be in."""
        env = self.env
        cells = self.victim_cells
        k = victim_at[tuple(cells.T)]
        v = jnp.maximum(k, 0)
        alive = jnp.where(jnp.asarray(env.victim_kind)[v] == 1, 3, 2)
        known = jnp.where(state.dead[v], 5, jnp.where(state.triaged[v], 4, alive))
        known = jnp.where(k >= 0, known, 1)
        return jnp.where(state.seen[tuple(cells.T)], known, 0)

    def view(self, state, victim_at) -> jax.Array:
        env = self.env
        h, w = env.height, env.width
        classes = self._cell_classes(state, victim_at)
        k = self.window
        padded = jnp.pad(classes, k, constant_values=WALL)
        shared = [jax.nn.one_hot(self._victim_cells(state, victim_at), len(VICTIM_CELL_CLASSES)).ravel()]
        if len(self.rubble_cells):
            shared.append(state.rubble[tuple(self.rubble_cells.T)].astype(jnp.float32))
        if env.expires:
            shared.append(time_bits(state.t, self.time_bits))
        shared = jnp.concatenate(shared)
        offsets = jnp.asarray(self.offsets)
        delta = jnp.asarray(np.asarray(env.dir_delta))
        rows = []
        for i in range(env.n_agents):
            pos, d = state.agent_pos[i], state.agent_dir[i]
            cells = pos + offsets[d] + k
            window = padded[cells[:, 0], cells[:, 1]]
            part = [jax.nn.one_hot(pos[0], h), jax.nn.one_hot(pos[1], w), jax.nn.one_hot(d, 4),
                    jnp.full((1,), float(env.roles[i] == 1)), jax.nn.one_hot(window, len(CELL_CLASSES)).ravel()]
            if self.staged:
                front = jnp.clip(pos + delta[d], 0, jnp.array([h - 1, w - 1]))
                inside = jnp.all(pos + delta[d] == front)
                v = victim_at[front[0], front[1]]
                shown = inside & (v >= 0) & state.seen[front[0], front[1]]
                shown = shown & ~state.triaged[jnp.maximum(v, 0)] & ~state.dead[jnp.maximum(v, 0)]
                part.append(jax.nn.one_hot(jnp.where(shown, state.progress[jnp.maximum(v, 0)], 0), int(env.needed.max())))
            rows.append(jnp.concatenate(part + [shared]))
        return jnp.stack(rows)
