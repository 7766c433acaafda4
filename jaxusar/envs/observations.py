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

from jaxusar.core.replay import OneHotCodec

# Classes of a cell in the egocentric window, in the priority they are assigned (first match wins).
CELL_CLASSES = ("wall", "agent", "rubble", "not seen", "regular victim", "critical victim",
                "triaged or dead victim", "floor")
WALL, AGENT, RUBBLE, NOT_SEEN, REGULAR_VICTIM, CRITICAL_VICTIM, DONE_VICTIM, FLOOR = range(len(CELL_CLASSES))
# What the team knows of a cell a victim may be in.
VICTIM_CELL_CLASSES = ("not seen", "no victim", "regular victim", "critical victim", "triaged", "dead")


def time_bits(t: jax.Array, n_bits: int) -> jax.Array:
    """int32[n_bits]: ``t`` in binary, least significant bit first."""
    return (t >> jnp.arange(n_bits)) & 1


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
        # per facing, the window's cells as indices into the north-up (2k+1)^2 patch around the agent
        self.turns = (self.offsets[..., 0] + self.window) * (2 * self.window + 1) + self.offsets[..., 1] + self.window
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
        self.full_codec, self.view_codec = OneHotCodec(self.full_blocks), OneHotCodec(self.view_blocks)
        self.drawn_cell_index = np.zeros((h, w), np.int32)  # a '?' cell's index among them
        self.drawn_cell_index[tuple(layout.random_cells.T)] = np.arange(len(layout.random_cells))

    # -- full ---------------------------------------------------------------------------------------
    def full_codes(self, state) -> jax.Array:
        """int32[len(full_blocks)]: the ``full`` observation, one code per block."""
        return jnp.concatenate(self.full_code_parts(state))

    def full_code_parts(self, state) -> list[jax.Array]:
        """``full_codes`` in pieces, in order (``OneHotCodec.decode`` takes them as they are)."""
        env = self.env
        parts = [p for i in range(env.n_agents) for p in (state.agent_pos[i], state.agent_dir[i:i + 1])]
        parts.append(state.triaged)
        if env.part1:
            return [p.astype(jnp.int32) for p in parts]
        if len(self.rubble_cells):
            parts.append(state.rubble[tuple(self.rubble_cells.T)])
        if env.n_drawn:
            drawn = state.victim_pos[env.n_fixed:]
            parts.append(jnp.asarray(self.drawn_cell_index)[drawn[:, 0], drawn[:, 1]])
        if self.staged:
            parts.append(state.progress[np.asarray(self.staged)])
        if env.expires:
            parts.append(state.dead[self.critical])
        parts.append(time_bits(state.t, self.time_bits))
        if len(self.unseen_at_reset):
            parts.append(state.seen[tuple(self.unseen_at_reset.T)])
        return [p.astype(jnp.int32) for p in parts]

    # -- view ---------------------------------------------------------------------------------------
    def _victim_codes(self, state) -> jax.Array:
        """int32[n_victims]: each victim's ``VICTIM_CELL_CLASSES`` index, as if seen."""
        alive = jnp.asarray(np.where(self.env.victim_kind == 1, 3, 2))
        return jnp.where(state.dead, 5, jnp.where(state.triaged, 4, alive))

    def view_codes(self, state, victim_at) -> jax.Array:
        """int32[n_agents, len(view_blocks)]: the ``view`` observation, one code per block.

        Every cell the view reads (window cells, victim cells, the cells in front) is looked up in one
        packed grid, padded by the window's radius with wall: bit 0 seen, bit 1 rubble, bit 2 wall, bit 3
        (in the windows) an agent, the victim index + 1 above. Elementwise work, slices and small gathers
        only: on CPU a scatter (of the agents or the victims into a grid) or a gather per cell of the
        grid costs more than the rest together."""
        env = self.env
        k = self.window
        grid = (victim_at + 1) * 16 + state.seen.astype(jnp.int32) + 4 * jnp.asarray(env.blocked, jnp.int32)
        if len(self.rubble_cells):
            grid = grid + 2 * state.rubble.astype(jnp.int32)
        grid = jnp.pad(grid, k, constant_values=4)
        codes = self._victim_codes(state)
        pos, d = state.agent_pos, state.agent_dir

        def look(cells):  # cells [..., 2] (grid coordinates) -> (seen, rubble, wall, victim index or -1)
            g = grid[cells[..., 0] + k, cells[..., 1] + k]
            return (g & 1) > 0, (g & 2) > 0, (g & 4) > 0, (g >> 4) - 1

        # Each window: a slice of the grid around the agent (north up), with a bit for the agents in it,
        # then turned to the agent's facing by a select among its four rotations.
        side = 2 * k + 1
        patch = jax.vmap(lambda p: jax.lax.dynamic_slice(grid, (p[0], p[1]), (side, side)))(pos).reshape(-1, side * side)
        rel = pos[None, :, :] - pos[:, None, :] + k  # [i, j, 2]: agent j in agent i's patch
        inside = jnp.all((rel >= 0) & (rel < side), -1)
        at = jnp.where(inside, rel[..., 0] * side + rel[..., 1], -1)
        patch = patch + 8 * jnp.any(at[:, :, None] == np.arange(side * side), 1)  # bit 3: an agent
        turns = [patch[:, order] for order in self.turns]
        g = jnp.select([d[:, None] == f for f in range(3)], turns[:3], turns[3])
        seen, rubble, wall, agent, v1 = (g & 1) > 0, (g & 2) > 0, (g & 4) > 0, (g & 8) > 0, g >> 4
        living = jnp.asarray(np.array([FLOOR, FLOOR, REGULAR_VICTIM, CRITICAL_VICTIM, DONE_VICTIM, DONE_VICTIM]))
        window = jnp.concatenate([jnp.array([FLOOR]), living[codes]])[v1]  # by victim index + 1
        window = jnp.where(seen, window, NOT_SEEN)
        window = jnp.where(rubble, RUBBLE, window)
        window = jnp.where(wall, WALL, jnp.where(agent, AGENT, window))

        seen, _, _, v = look(jnp.asarray(self.victim_cells))  # what the team knows of each victim cell
        team = [jnp.where(seen, jnp.where(v >= 0, codes[jnp.maximum(v, 0)], 1), 0)]
        if len(self.rubble_cells):
            team.append(state.rubble[tuple(self.rubble_cells.T)])
        own = [pos, d[:, None], jnp.asarray(env.roles == 1, jnp.int32)[:, None], window]
        tail = []
        if self.staged:  # the progress of the victim in front, where it is seen and still needs triage
            seen, _, _, v = look(pos + jnp.asarray(np.asarray(env.dir_delta))[d])
            shown = seen & (v >= 0) & (codes[jnp.maximum(v, 0)] < 4)
            tail.append(jnp.where(shown, state.progress[jnp.maximum(v, 0)], 0)[:, None])
        if env.expires:
            tail.append(jnp.broadcast_to(time_bits(state.t, self.time_bits), (env.n_agents, self.time_bits)))
        team = jnp.concatenate([x.astype(jnp.int32) for x in team])
        rows = own + [jnp.broadcast_to(team, (env.n_agents, len(team)))] + tail
        return jnp.concatenate([r.astype(jnp.int32) for r in rows], 1)

    def full(self, state) -> jax.Array:
        """float32[obs_dim]: the ``full`` observation (its codes' one-hot blocks)."""
        return self.full_codec.decode(self.full_codes(state))

    def view(self, state, victim_at) -> jax.Array:
        """float32[n_agents, obs_dim]: the ``view`` observation (its codes' one-hot blocks)."""
        return self.view_codec.decode(self.view_codes(state, victim_at))
