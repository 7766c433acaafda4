"""The exact joint search: breadth-first over the joint state of every agent, in time layers.

The successors are the env's own ``step`` (jit + vmap over the layer and every joint action), so the planner
and the learners share one definition of the rules. A planning state is an integer (``_Codec``): each agent's
(row, col, dir); then per victim its triage progress (one bit, triaged or not, unless some victim needs more
than one TRIAGE: then 0..needed, needed = triaged); then, on maps with rubble and engineers, one bit per
rubble cell of the layout (still there or cleared). A map's features it does not use are not encoded (the
env's static flags), so part 1's maps keep part 1's codes. ``t`` is not encoded: layer t holds the states
first reached after t joint steps, and the dead victims of a state in it are a function of its triaged
flags and t (a critical victim not triaged is dead once t >= critical_expires). De-duplication is across
layers (numpy set operations), so memory grows with the reachable states, not the product space; keeping
only a state's first visit is exact for the fewest steps and also for the highest return, since a state
reached earlier can do whatever the same state reached later can (DESIGN.md contract part 2: no victim
revives, rewards are not negative, the penalty per step is not positive; ``optimal.py`` checks this).

``_search`` finds the fewest steps to a goal (optionally pruning states, ``optimal.py``); ``_layered`` is the
layer loop under it, and under the highest-return search.
"""

from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxusar.envs.layout import CRITICAL
from jaxusar.envs.usar import N_ACTIONS, EnvState, USAREnv


class Unreachable(RuntimeError):
    """The goal cannot be reached from the start state."""


class SearchTooLarge(MemoryError):
    """The exact joint search would visit more states than it may (raised before searching when even the
    map's bound on joint states is far past the limit)."""


class States(NamedTuple):
    """A batch of planning states (numpy): pos int32[N, n_agents, 2]; dirs int32[N, n_agents]; progress
    int32[N, n_victims] (TRIAGE actions received, capped at the victim's needed: that is triaged);
    triaged bool[N, n_victims]; rubble bool[N, R] (the codec's rubble cells still there; R = 0 where the
    rubble cannot change)."""

    pos: np.ndarray
    dirs: np.ndarray
    progress: np.ndarray
    triaged: np.ndarray
    rubble: np.ndarray

    def take(self, index) -> "States":
        return States(*(x[index] for x in self))


class _Codec:
    """Mixed-radix integer <-> ``States`` (see the module doc for the fields and their order)."""

    def __init__(self, env: USAREnv):
        self.width = env.width
        self.cell_states = env.height * env.width * 4
        self.n_agents, self.n_victims = env.n_agents, env.n_victims
        # one TRIAGE per victim unless the map says otherwise: then the radix is needed + 1 (0..needed)
        self.needed = np.asarray(env.needed if env.multi_step else np.ones(env.n_victims), np.int64)
        dynamic = env.has_rubble and env.has_engineers  # without engineers rubble never changes
        self.rubble_cells = np.argwhere(env.layout.rubble if dynamic else np.zeros((1, 1), bool)).astype(np.int32)
        radices = [self.cell_states] * self.n_agents + [int(k) + 1 for k in self.needed] + [2] * len(self.rubble_cells)
        if math.prod(radices) >= 2 ** 63:
            raise SearchTooLarge(f"the joint states of {env.layout.name!r} do not fit in a 64-bit code "
                                 f"({self.n_agents} agents, {self.n_victims} victims, {len(self.rubble_cells)} rubble "
                                 "cells): too large for the exact search")

    def of(self, state: EnvState) -> States:
        """The planning state of one (unbatched, complete) env state, as a batch of one."""
        rubble = np.asarray(state.rubble)[tuple(self.rubble_cells.T)]
        progress = np.minimum(np.asarray(state.progress), self.needed).astype(np.int32)
        return States(np.asarray(state.agent_pos)[None], np.asarray(state.agent_dir)[None], progress[None],
                      np.asarray(state.triaged)[None], rubble[None])

    def encode(self, s: States) -> np.ndarray:
        code = np.zeros(len(s.dirs), np.int64)
        for i in range(self.n_agents):
            cell = (s.pos[:, i, 0].astype(np.int64) * self.width + s.pos[:, i, 1]) * 4 + s.dirs[:, i]
            code = code * self.cell_states + cell
        for v in range(self.n_victims):
            code = code * (self.needed[v] + 1) + s.progress[:, v]
        for k in range(len(self.rubble_cells)):
            code = code * 2 + s.rubble[:, k]
        return code

    def decode(self, code: np.ndarray) -> States:
        code = code.astype(np.int64).copy()
        rubble = np.zeros((len(code), len(self.rubble_cells)), bool)
        for k in reversed(range(len(self.rubble_cells))):
            rubble[:, k] = code % 2
            code //= 2
        progress = np.zeros((len(code), self.n_victims), np.int32)
        for v in reversed(range(self.n_victims)):
            progress[:, v] = code % (self.needed[v] + 1)
            code //= self.needed[v] + 1
        pos = np.zeros((len(code), self.n_agents, 2), np.int32)
        dirs = np.zeros((len(code), self.n_agents), np.int32)
        for i in reversed(range(self.n_agents)):
            cell = code % self.cell_states
            code //= self.cell_states
            dirs[:, i] = cell % 4
            pos[:, i, 0] = (cell // 4) // self.width
            pos[:, i, 1] = (cell // 4) % self.width
        return States(pos, dirs, progress, progress >= self.needed, rubble)


def _joint_actions(n_agents: int) -> np.ndarray:
    """int32[N_ACTIONS ** n_agents, n_agents]: every joint action; row k is the expander's k-th successor."""
    return np.asarray(list(itertools.product(range(N_ACTIONS), repeat=n_agents)), np.int32).reshape(-1, n_agents)


def _expander(env: USAREnv):
    """The jitted successor function of ``env``'s rules. Cached by what the step rules read (solid cells,
    victims, roles, rubble cells, triage steps, expiry), not by the env object, so every ``make`` of one map
    shares one compile; the start state (drawn victims included) is an argument, so every draw of a map
    with victims drawn at reset shares it too."""
    arrays = (env._solid, env._victim_at, env.roles, env.layout.rubble, env.needed, env.victim_kind)
    rules = (tuple((a.tobytes(), a.shape) for a in arrays), env.n_agents, env.n_drawn, env.critical_expires,
             env.has_rubble, env.has_engineers, env.multi_step, env.expires)
    if rules not in _EXPANDERS:
        _EXPANDERS[rules] = _make_expander(env)
    return _EXPANDERS[rules]


_EXPANDERS: dict = {}


def _make_expander(env: USAREnv):
    joint = jnp.asarray(_joint_actions(env.n_agents))
    cells = _Codec(env).rubble_cells
    needed = jnp.asarray(_Codec(env).needed, jnp.int32)
    critical = jnp.asarray(env.victim_kind == CRITICAL)

    def successors(base, pos, dirs, progress, rubble, t):
        n = pos.shape[0]
        state = jax.tree.map(lambda x: jnp.broadcast_to(x, (n, *x.shape)), base)
        triaged = progress >= needed
        fields = dict(agent_pos=pos, agent_dir=dirs, triaged=triaged, progress=progress,
                      t=jnp.broadcast_to(t, (n,)).astype(jnp.int32))
        if len(cells):
            fields["rubble"] = state.rubble.at[:, cells[:, 0], cells[:, 1]].set(rubble)
        if env.expires:  # dead = f(triaged, t): the layers are time
            fields["dead"] = critical & ~triaged & (t >= env.critical_expires)
        state = state.replace(**fields)

        def one(s):
            return jax.vmap(lambda a: env.step(None, s, a)[1])(joint)

        nxt = jax.vmap(one)(state)
        nrubble = nxt.rubble[:, :, cells[:, 0], cells[:, 1]] if len(cells) else jnp.zeros((*nxt.t.shape, 0), bool)
        nprogress = nxt.progress if env.multi_step else nxt.triaged.astype(jnp.int32)
        return nxt.agent_pos, nxt.agent_dir, nprogress, nrubble

    return jax.jit(successors)


def _layered(env: USAREnv, start: EnvState, on_layer, max_states: int, record: bool = False,
             stats: dict | None = None) -> None:
    """Breadth-first search in time layers from ``start``, each state kept at its first visit.

    ``on_layer(depth, states, plan_to)`` sees each layer (``States``, sorted by code) and returns a bool mask
    of the states to expand (``True``: all), or None to stop. With ``record``, ``plan_to(i)`` is one joint
    plan int32[depth, n_agents] from ``start`` to the layer's state ``i``: per depth, each new state keeps the
    parent and joint action that first reached it; ties go to the smallest state code and the first joint
    action, so plans are deterministic. ``stats`` (a dict), if given, holds the states visited and the
    depth reached so far. Raises MemoryError past ``max_states`` visited states.
    """
    stats = {} if stats is None else stats
    codec, expand = _Codec(env), _expander(env)
    start = env.complete(start)
    n_joint = N_ACTIONS ** env.n_agents
    # states per call: a power of 8, a few million successors at most; calls are padded to powers of 8 from
    # 64: each size compiles once (seconds), running a padded call costs far less
    chunk = 8 ** max(2, int(np.log2((1 << 21) // n_joint)) // 3)
    layer = codec.encode(codec.of(start))
    visited = layer
    depth = 0
    layers = []  # with record: per depth >= 1, (parent index in the previous layer, joint action index)

    def plan_to(index: int) -> np.ndarray:
        return _backtrack(layers, index, env.n_agents)

    while True:
        states = codec.decode(layer)
        keep = on_layer(depth, states, plan_to)
        if keep is None:
            return
        expand_idx = np.arange(len(layer)) if keep is True else np.flatnonzero(keep)
        if not len(expand_idx):
            return
        t = jnp.asarray(int(start.t) + depth, jnp.int32)
        codes, parents, actions = [], [], []
        for lo in range(0, len(expand_idx), chunk):
            part = expand_idx[lo:lo + chunk]
            sub = states.take(part)
            pad = 64
            while pad < len(part):
                pad *= 8
            padded = [np.concatenate([x, np.repeat(x[:1], pad - len(x), 0)])
                      for x in (sub.pos, sub.dirs, sub.progress, sub.rubble)]
            out = [np.asarray(x)[: len(part)] for x in expand(start, *padded, t)]
            new = codec.encode(States(out[0].reshape(-1, env.n_agents, 2), out[1].reshape(-1, env.n_agents),
                                      out[2].reshape(-1, env.n_victims), None,
                                      out[3].reshape(len(part) * n_joint, len(codec.rubble_cells))))
            if record:  # new is row-major [state, joint action]: first = parent * n_joint + action
                new, first = np.unique(new, return_index=True)
                fresh = ~np.isin(new, visited, assume_unique=True)
                parent, action = np.divmod(first[fresh], n_joint)
                codes.append(new[fresh]), parents.append(part[parent]), actions.append(action)
            else:
                codes.append(np.setdiff1d(np.unique(new), visited, assume_unique=True))
        if record:  # across chunks, the first occurrence is still the smallest parent, then the first action
            layer, first = np.unique(np.concatenate(codes), return_index=True)
            layers.append((np.concatenate(parents)[first], np.concatenate(actions)[first]))
        else:
            layer = np.unique(np.concatenate(codes))
        visited = np.union1d(visited, layer)
        depth += 1
        stats.update(visited=int(len(visited)), depth=depth)
        if len(visited) > max_states:
            raise MemoryError(f"planner visited over {max_states} states on {env.layout.name!r}; "
                              "raise max_states or plan on a smaller map")
        if not len(layer):
            return


def _search(env: USAREnv, start: EnvState, is_goal, max_states: int, record: bool = False,
            stats: dict | None = None, prune=None):
    """Breadth-first search from ``start`` to a state where ``is_goal(pos, dirs, triaged)`` holds.

    Returns ``(depth, plan)``: the fewest joint steps, and with ``record`` one shortest plan int32[depth,
    n_agents] (else None; ties as in ``_layered``). ``prune(depth, states)``, if given, is a bool mask of
    the states worth expanding (an admissible cut keeps the answer exact). ``stats`` as in ``_layered``.
    Raises Unreachable when the search ends without a goal.
    """
    found = {}

    def on_layer(depth, states, plan_to):
        goal = np.flatnonzero(is_goal(states.pos, states.dirs, states.triaged))
        if len(goal):
            found.update(depth=depth, plan=plan_to(goal[0]) if record else None)
            return None
        return True if prune is None else prune(depth, states)

    _layered(env, start, on_layer, max_states, record, stats)
    if not found:
        raise Unreachable(f"goal unreachable on {env.layout.name!r}")
    return found["depth"], found["plan"]


def _backtrack(layers, index: int, n_agents: int) -> np.ndarray:
    """Joint actions leading to state ``index`` of the last layer, following recorded parents."""
    joint, plan = _joint_actions(n_agents), []
    for parent, action in reversed(layers):
        plan.append(joint[action[index]])
        index = parent[index]
    return np.asarray(plan[::-1], np.int32).reshape(-1, n_agents)


def _bfs(env: USAREnv, start: EnvState, is_goal, max_states: int) -> int:
    """Fewest joint steps from ``start`` to a state where ``is_goal(pos, dirs, triaged)`` holds."""
    return _search(env, start, is_goal, max_states)[0]


def _all_triaged(pos, dirs, triaged) -> np.ndarray:
    return triaged.all(-1)


def joint_states_bound(env: USAREnv) -> int:
    """An upper bound on the joint states the exact search may visit: (open cells x 4)^agents x the victims'
    progress values (2 each with one-step triage: triaged or not) x 2^rubble cells (where engineers clear)."""
    progress = math.prod(int(k) + 1 for k in _Codec(env).needed)
    rubble = 2 ** int(env.layout.rubble.sum()) if env.has_rubble and env.has_engineers else 1
    return (int((~env.layout.blocked).sum()) * 4) ** env.n_agents * progress * rubble


def _check_size(env: USAREnv, max_states: int) -> None:
    """Refuse before searching when the joint-state bound is far past ``max_states``: 100x on part 1's maps
    (the plain search visits about a tenth of it on two_rooms), 10,000x elsewhere, where the search cuts
    the states that cannot finish in time (``optimal.py``; two_rooms_rubble: 9.5e4 of 2.5e9)."""
    bound = joint_states_bound(env)
    if bound > (100 if env.part1 else 10_000) * max_states:
        raise SearchTooLarge(
            f"the exact optimum of {env.layout.name!r} ({env.n_agents} agents, {env.n_victims} victims) needs a joint "
            f"search over up to {bound:.2g} states, past the planner's limit of {max_states:.2g}; training there "
            "measures teams against planning.team_lower_bound instead (planning.team_reference)")


def agent_distances(env: USAREnv, agent: int, start_pos=None, start_dir=None) -> dict[str, np.ndarray]:
    """Shortest single-agent distances for ``agent`` alone on the map (other agents removed).

    Returns ``to_region`` int[R] (steps until the agent stands in region r; 0 if it starts there) and
    ``to_triage`` int[n_victims] (steps until victim v is triaged, the TRIAGE action included).
    Unreachable entries are -1. ``start_pos``/``start_dir`` default to the agent's reset state.
    """
    from jaxusar.envs import USAREnv as _Env

    if not 0 <= agent < env.n_agents:
        raise ValueError(f"agent {agent} out of range 0..{env.n_agents - 1}")
    solo = _Env(env.layout.subset(agents=[agent]), horizon=env.horizon, start_dir=env.start_dir)
    start = solo.initial_state()
    if start_pos is not None:
        start = start.replace(agent_pos=jnp.asarray([start_pos], jnp.int32))
    if start_dir is not None:
        start = start.replace(agent_dir=jnp.asarray([start_dir], jnp.int32))
    region = env.graph.cell_region

    def steps(goal):
        try:
            return _bfs(solo, start, goal, max_states=10_000_000)
        except Unreachable:
            return -1

    to_region = [steps(lambda p, d, t, r=r: region[p[:, 0, 0], p[:, 0, 1]] == r) for r in range(env.graph.n_regions)]
    to_triage = [steps(lambda p, d, t, v=v: t[:, v]) for v in range(env.n_victims)]
    return {"to_region": np.asarray(to_region), "to_triage": np.asarray(to_triage)}
