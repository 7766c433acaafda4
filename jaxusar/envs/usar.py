"""The USAR grid world as pure, jit-able, vmap-able functions (paper Sec. IV-A; contract in DESIGN.md).

Agents move on a grid, turn, and use their role's tool: medics triage victims, engineers clear rubble.
The map is static (numpy arrays closed over by ``jit``); the state is a small pytree, so
``jax.vmap(env.step)`` runs many worlds at once, and ``jax.vmap(env.reset)(keys)`` draws many placements.

Step semantics (fixed contract, parts 1 and 2): agents act in index order. FORWARD moves one cell into an
in-bounds, unblocked cell holding no victim (triaged, dead or not), no rubble (as cleared so far this
step) and no other agent (as already moved this step); TURN_LEFT = (dir + 3) % 4, TURN_RIGHT =
(dir + 1) % 4. Action 3 (TRIAGE) is the role's tool: an engineer facing rubble clears it; a medic facing
a victim neither triaged nor dead adds 1 to its progress, and the victim is triaged when its progress
reaches its kind's triage steps; otherwise a no-op. Then ``t += 1``; then every critical victim not
triaged with ``t >= critical_expires`` is dead; then the team's ``seen`` adds every cell some agent sees
(a cell of its own region within Chebyshev distance ``view_radius``). Reward = triage_reward x newly
triaged regular + critical_reward x newly triaged critical + step_penalty. ``done`` when every victim is
triaged or dead, or ``t`` reaches the horizon. ``step`` never resets: stepping a done state goes on
(``t`` keeps counting, nothing else changes but what the actions do); callers reset.

A map's features it does not use cost nothing in its step: whether it has rubble, engineers, drawn
victims, multi-step triage or expiry are Python flags read at trace time.

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
from jaxusar.envs.layout import CRITICAL, ENGINEER, HEADER_KEYS, Layout, check_victims, header_value
from jaxusar.core.replay import OneHotCodec
from jaxusar.envs.observations import Encoder

EAST, SOUTH, WEST, NORTH = 0, 1, 2, 3
DIRECTION_NAMES = ("EAST", "SOUTH", "WEST", "NORTH")
FORWARD, TURN_LEFT, TURN_RIGHT, TRIAGE = 0, 1, 2, 3
ACTION_NAMES = ("FORWARD", "TURN_LEFT", "TURN_RIGHT", "TRIAGE")
N_ACTIONS = 4
# How an observation is given: one-hot float32 blocks (the contract's), or one integer code per block.
ENCODINGS = ("one_hot", "codes")
# (d_row, d_col) of one FORWARD step per direction, in Minigrid order.
DIR_DELTA = np.array([[0, 1], [1, 0], [0, -1], [-1, 0]], dtype=np.int32)


@struct.dataclass
class EnvState:
    """agent_pos int32[n_agents, 2] (row, col); agent_dir int32[n_agents]; triaged bool[n_victims]; t int32;
    victim_pos int32[n_victims, 2] (drawn at reset); rubble bool[H, W] (not yet cleared); progress
    int32[n_victims] (TRIAGE actions received); dead bool[n_victims] (expired critical victims);
    seen bool[H, W] (cells the team has seen).

    ``USAREnv`` always returns every field. The part-2 fields default to None so that part 1's
    four-field state still works: ``USAREnv.complete`` fills them in as at reset.
    """

    agent_pos: jax.Array
    agent_dir: jax.Array
    triaged: jax.Array
    t: jax.Array
    victim_pos: jax.Array | None = None
    rubble: jax.Array | None = None
    progress: jax.Array | None = None
    dead: jax.Array | None = None
    seen: jax.Array | None = None


def apply_rules(solid, victim_at, agent_pos, agent_dir, triaged, actions, *, roles=None, rubble=None,
                progress=None, needed=None, dead=None):
    """The step rules on plain arrays (the one implementation every env here uses).

    solid bool[H, W]: cells no agent may enter (blocked or holding a victim); victim_at int32[H, W]:
    victim index per cell, -1 elsewhere. Map arrays may be traced, so a batch of different maps or
    tasks can be vmapped. The part-2 arguments are off where None (a Python-level flag: no cost):
    ``roles`` (numpy int[n_agents]; None = all medics), ``rubble`` bool[H, W], ``progress`` int32[V]
    with ``needed`` int32[V] (TRIAGE actions each victim needs; None = one), ``dead`` bool[V].
    Returns (agent_pos, agent_dir, triaged, newly_triaged, rubble, progress).
    """
    height, width = solid.shape
    n_agents, n_victims = agent_dir.shape[0], triaged.shape[0]
    pos, dirs = agent_pos, agent_dir
    newly = jnp.zeros_like(triaged)
    for i in range(n_agents):  # index order: agent i sees agents < i already moved, rubble already cleared
        a, d = actions[i], dirs[i]
        front = pos[i] + jnp.asarray(DIR_DELTA)[d]
        inside = (front[0] >= 0) & (front[0] < height) & (front[1] >= 0) & (front[1] < width)
        front = jnp.clip(front, 0, jnp.array([height - 1, width - 1]))
        others = jnp.arange(n_agents) != i
        occupied = jnp.any(others & jnp.all(pos == front, axis=-1))
        free = inside & ~solid[front[0], front[1]] & ~occupied
        if rubble is not None:
            free = free & ~rubble[front[0], front[1]]
        can_move = (a == FORWARD) & free
        pos = pos.at[i].set(jnp.where(can_move, front, pos[i]))
        turned = jnp.where(a == TURN_LEFT, (d + 3) % 4, jnp.where(a == TURN_RIGHT, (d + 1) % 4, d))
        dirs = dirs.at[i].set(turned)
        if roles is not None and roles[i] == ENGINEER:  # an engineer's tool clears the rubble in front
            if rubble is not None:
                clear = (a == TRIAGE) & inside
                rubble = rubble.at[front[0], front[1]].set(rubble[front[0], front[1]] & ~clear)
            continue
        victim = jnp.where(inside, victim_at[front[0], front[1]], -1)
        hit = (a == TRIAGE) & (jnp.arange(n_victims) == victim) & ~triaged
        if dead is not None:
            hit = hit & ~dead
        if progress is not None:
            progress = progress + hit.astype(progress.dtype)
            hit = hit & (progress >= needed)
        newly, triaged = newly | hit, triaged | hit
    return pos, dirs, triaged, newly, rubble, progress


def apply_actions(solid, victim_at, agent_pos, agent_dir, triaged, actions):
    """Part 1's rules (medics only, one-step triage): ``apply_rules`` without its part-2 arguments.
    Returns (agent_pos, agent_dir, triaged, newly_triaged)."""
    return apply_rules(solid, victim_at, agent_pos, agent_dir, triaged, actions)[:4]


def draw_without_replacement(key: jax.Array, n: int, k: int) -> jax.Array:
    """int32[k]: k distinct indices of 0..n-1, uniformly without replacement (every ordered k-subset equally
    likely): the first k steps of a Fisher-Yates shuffle, the j-th pick uniform among the n - j not yet
    drawn. k uniforms and k swaps instead of a sort of n random keys (``jax.random.choice(replace=False)``,
    20x slower vmapped on CPU), which would dominate a vmapped auto-reset."""
    u = jax.random.uniform(key, (k,))
    perm = jnp.arange(n, dtype=jnp.int32)
    for j in range(k):
        r = j + jnp.minimum((u[j] * (n - j)).astype(jnp.int32), n - j - 1)  # among positions j..n-1
        perm = perm.at[r].set(perm[j]).at[j].set(perm[r])
    return perm[:k]


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
    ``victim_pos`` int32[n_victims, 2] (-1 on the rows of victims drawn at reset), ``roles``
    int32[n_agents] (0 MEDIC, 1 ENGINEER), ``victim_kind`` int32[n_victims] (0 REGULAR, 1 CRITICAL),
    ``n_agents``, ``n_victims`` (``n_fixed`` from the layout, then ``n_drawn``), ``horizon``,
    ``triage_reward``, ``step_penalty``, ``start_dir``, and the map settings of ``layout.HEADER_KEYS``
    (``random_victims``, ``triage_steps``, ``critical_triage_steps``, ``critical_reward``,
    ``critical_expires``, ``view_radius``, ``observation``); ``needed`` int32[n_victims], the TRIAGE
    actions each victim needs; ``part1``, whether the map uses no part-2 feature.

    Observation (``jaxusar.envs.observations``): ``observation="full"`` is float32[obs_dim], part 1's
    vector on a part-1 map (per agent one-hot(row, H), one-hot(col, W), one-hot(dir, 4), then the
    victims' triaged flags: 2 x (10 + 15 + 4) + 2 = 60 numbers on two_rooms) and elsewhere that vector
    with what else determines the state. ``observation="view"`` is float32[n_agents, obs_dim]: each
    agent's pose, an egocentric window rotated to its facing, the floor plan's rubble, and victims only
    in cells the team has seen. ``obs_blocks`` are the widths of one row's one-hot blocks, ``obs_dim``
    their sum. With ``encoding="codes"`` each block is given as one integer instead (``obs_codec``, a
    ``core.replay.OneHotCodec``: the index of its 1, a flag's value), uint8 where every block is narrower
    than 256, and ``obs_codec.decode`` gives the float observation back; the same information in
    1/10 to 1/20 of the numbers, for learners that embed or look up codes. ``obs_shape`` and
    ``obs_dtype`` are those of the observation as given.
    """

    def __init__(self, layout: Layout, horizon: int = 100, triage_reward: float = 100.0,
                 step_penalty: float = 0.0, start_dir: int | str = NORTH, encoding: str = "one_hot", **settings):
        if isinstance(start_dir, str):
            if start_dir.upper() not in DIRECTION_NAMES:
                raise ValueError(f"override start_dir={start_dir!r}: expected one of {DIRECTION_NAMES} or 0..3")
            start_dir = DIRECTION_NAMES.index(start_dir.upper())
        _check_override("horizon", horizon, int, 1, 1_000_000)
        _check_override("triage_reward", triage_reward, float)
        _check_override("step_penalty", step_penalty, float)
        _check_override("start_dir", start_dir, int, 0, 3)
        if encoding not in ENCODINGS:
            raise ValueError(f"override encoding={encoding!r}: expected one of {', '.join(ENCODINGS)}")
        map_settings = {**HEADER_KEYS, **layout.header}
        for key, value in settings.items():
            map_settings[key] = header_value(key, value, f"map {layout.name!r}, override")
        check_victims(layout, map_settings["random_victims"])
        self.layout = layout
        self.graph = RegionGraph(layout)
        self.horizon = int(horizon)
        self.triage_reward = float(triage_reward)
        self.step_penalty = float(step_penalty)
        self.start_dir = int(start_dir)
        self.encoding = encoding
        for key, value in map_settings.items():
            setattr(self, key, value)
        self.height, self.width = layout.shape
        self.dir_delta = DIR_DELTA
        self.blocked = layout.blocked
        self.roles = np.asarray(layout.roles, np.int32)
        self.n_agents = len(layout.agent_start)
        n_regular, n_critical = self.random_victims
        self.n_fixed, self.n_drawn = len(layout.victim_pos), n_regular + n_critical
        self.n_victims = self.n_fixed + self.n_drawn
        self.victim_kind = np.concatenate([layout.victim_kind, np.zeros(n_regular), np.ones(n_critical)]).astype(np.int32)
        self.victim_pos = np.concatenate([layout.victim_pos, np.full((self.n_drawn, 2), -1)]).astype(np.int32)
        self.needed = np.where(self.victim_kind == CRITICAL, self.critical_triage_steps, self.triage_steps).astype(np.int32)
        # Python-level feature flags: what a map does not use is not traced into its step.
        self.has_rubble = bool(layout.rubble.any())
        self.has_engineers = bool(np.any(self.roles == ENGINEER))
        self.multi_step = bool(self.needed.max() > 1)
        self.expires = self.critical_expires is not None and bool(np.any(self.victim_kind == CRITICAL))
        self.part1 = not (self.has_rubble or self.has_engineers or self.n_drawn or self.multi_step
                          or np.any(self.victim_kind == CRITICAL))
        # A cell an agent may not enter: blocked or holding a (fixed) victim.
        solid = self.blocked.copy()
        solid[tuple(layout.victim_pos.T)] = True
        self._solid = solid
        victim_at = np.full(layout.shape, -1, np.int32)
        victim_at[tuple(layout.victim_pos.T)] = np.arange(self.n_fixed)
        self._victim_at = victim_at
        self.seen_at_reset = np.asarray(self._sees(jnp.asarray(layout.agent_start, jnp.int32)))
        self._encoder = Encoder(self)
        blocks = self._encoder.full_blocks if self.observation == "full" else self._encoder.view_blocks
        self.obs_blocks = tuple(blocks)  # one-hot widths of one observation row
        self.obs_codec = OneHotCodec(self.obs_blocks)
        self.obs_dim = sum(self.obs_blocks)
        row = self.obs_dim if encoding == "one_hot" else len(self.obs_blocks)
        self.obs_shape = (row,) if self.observation == "full" else (self.n_agents, row)
        self.obs_dtype = jnp.float32 if encoding == "one_hot" else self.obs_codec.dtype

    def __repr__(self) -> str:
        extra = "".join(f", {k}={getattr(self, k)!r}" for k, v in HEADER_KEYS.items() if getattr(self, k) != v)
        return (f"USAREnv({self.layout.name!r}, {self.height}x{self.width}, agents={self.n_agents}, "
                f"victims={self.n_victims}, horizon={self.horizon}, triage_reward={self.triage_reward}, "
                f"step_penalty={self.step_penalty}, start_dir={DIRECTION_NAMES[self.start_dir]}{extra})")

    # -- pure functions ------------------------------------------------------------------------
    def _sees(self, agent_pos: jax.Array) -> jax.Array:
        """bool[H, W]: the cells some agent at ``agent_pos`` sees (its region, within ``view_radius``)."""
        region = jnp.asarray(self.graph.cell_region)[agent_pos[:, 0], agent_pos[:, 1]]
        # a compare with the static region grid, which fuses into the caller's OR (a gather of [H, W] masks
        # does not, and cost two_rooms ~10% of its env-steps/s)
        sees = jnp.asarray(self.graph.cell_region)[None] == region[:, None, None]  # [n_agents, H, W]
        if self.view_radius is not None:
            near_row = jnp.abs(jnp.arange(self.height)[None, :] - agent_pos[:, :1]) <= self.view_radius
            near_col = jnp.abs(jnp.arange(self.width)[None, :] - agent_pos[:, 1:]) <= self.view_radius
            sees = sees & near_row[:, :, None] & near_col[:, None, :]
        return sees.any(0)

    def _victim_cells(self, state: EnvState) -> tuple[jax.Array, jax.Array]:
        """(solid bool[H, W], victim_at int32[H, W]) of ``state``: static unless victims are drawn."""
        if not self.n_drawn:
            return jnp.asarray(self._solid), jnp.asarray(self._victim_at)
        pos = state.victim_pos
        victim_at = jnp.full(self.blocked.shape, -1, jnp.int32).at[pos[:, 0], pos[:, 1]].set(jnp.arange(self.n_victims))
        return jnp.asarray(self.blocked) | (victim_at >= 0), victim_at

    def initial_state(self, key: jax.Array | None = None) -> EnvState:
        """The reset state; ``key`` draws the victims of ``random_victims`` (uniformly without replacement
        among the '?' cells: regular ones first, then critical), and is needed only then."""
        victim_pos = jnp.asarray(self.victim_pos)
        if self.n_drawn:
            if key is None:
                raise ValueError(f"map {self.layout.name!r} draws victims at reset: pass a PRNG key")
            cells = draw_without_replacement(key, len(self.layout.random_cells), self.n_drawn)
            victim_pos = victim_pos.at[self.n_fixed:].set(jnp.asarray(self.layout.random_cells)[cells])
        return EnvState(
            agent_pos=jnp.asarray(self.layout.agent_start, jnp.int32),
            agent_dir=jnp.full((self.n_agents,), self.start_dir, jnp.int32),
            triaged=jnp.zeros((self.n_victims,), bool),
            t=jnp.zeros((), jnp.int32),
            victim_pos=victim_pos,
            rubble=jnp.asarray(self.layout.rubble),
            progress=jnp.zeros((self.n_victims,), jnp.int32),
            dead=jnp.zeros((self.n_victims,), bool),
            seen=jnp.asarray(self.seen_at_reset),
        )

    def reset(self, key: jax.Array) -> tuple[jax.Array, EnvState]:
        """The fixed starts; victims drawn with ``key`` where the map has ``random_victims``."""
        state = self.initial_state(key if self.n_drawn else None)
        return self.observe(state), state

    def complete(self, state: EnvState) -> EnvState:
        """``state`` with any part-2 field left None (a state built with part 1's four fields) filled in
        as at reset (``seen``: from the starts); the victims' progress follows their triaged flags."""
        missing = {f: None for f in ("victim_pos", "rubble", "dead", "seen") if getattr(state, f) is None}
        if not missing and state.progress is not None:
            return state
        if "victim_pos" in missing and self.n_drawn:
            raise ValueError(f"map {self.layout.name!r} draws victims at reset: a state needs victim_pos")
        batch = state.t.shape
        start = jax.tree.map(lambda x: jnp.broadcast_to(x, (*batch, *x.shape)), self.initial_state())
        filled = {f: getattr(start, f) for f in missing}
        if state.progress is None:
            filled["progress"] = state.triaged.astype(jnp.int32)
        return state.replace(**filled)

    def observe(self, state: EnvState) -> jax.Array:
        """The observation of ``state`` (``observation``: ``full`` or ``view``; ``encoding``: one-hot
        float32, or ``codes``, one integer per block; see the class doc)."""
        state = self.complete(state)
        enc = self._encoder
        if self.observation == "full":
            codes = enc.full_code_parts(state)  # decoded piece by piece, or concatenated
        else:
            codes = [enc.view_codes(state, self._victim_cells(state)[1])]
        if self.encoding == "one_hot":
            return self.obs_codec.decode(codes)
        return jnp.concatenate(codes, -1).astype(self.obs_dtype)

    def step(self, key: jax.Array, state: EnvState, actions: jax.Array):
        """One joint step. Returns (obs, state, reward float32, done bool, info).

        info: ``newly_triaged`` bool[n_victims]; ``terminated`` (every victim triaged or dead);
        ``truncated`` (horizon reached with victims left).
        """
        del key
        actions = self._check_actions(actions)
        state = self.complete(state)
        solid, victim_at = self._victim_cells(state)
        pos, dirs, triaged, newly, rubble, progress = apply_rules(
            solid, victim_at, state.agent_pos, state.agent_dir, state.triaged, actions,
            roles=self.roles if self.has_engineers else None, rubble=state.rubble if self.has_rubble else None,
            progress=state.progress if self.multi_step else None, needed=jnp.asarray(self.needed),
            dead=state.dead if self.expires else None)
        t = state.t + 1
        dead = state.dead
        if self.expires:
            dead = dead | ((jnp.asarray(self.victim_kind) == CRITICAL) & ~triaged & (t >= self.critical_expires))
        state = state.replace(agent_pos=pos, agent_dir=dirs, triaged=triaged, t=t,
                              rubble=state.rubble if rubble is None else rubble,
                              progress=triaged.astype(jnp.int32) if progress is None else progress,
                              dead=dead, seen=state.seen | self._sees(pos))
        if np.any(self.victim_kind == CRITICAL):
            worth = jnp.asarray(np.where(self.victim_kind == CRITICAL, self.critical_reward, self.triage_reward),
                                jnp.float32)
            reward = (jnp.sum(newly * worth) + self.step_penalty).astype(jnp.float32)
        else:
            reward = (self.triage_reward * newly.sum() + self.step_penalty).astype(jnp.float32)
        terminated = jnp.all(triaged | dead)
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
