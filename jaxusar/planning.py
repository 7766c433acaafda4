"""Exact planning by breadth-first search: the ground truth that defines "optimal" (PAPER.md).

The search runs the env's own ``step`` (jit + vmap over the frontier and every joint action), so the
planner and the learners share one definition of the rules. States are encoded as integers
(each agent's (row, col, dir), then the triaged bits) and de-duplicated with numpy set operations,
so memory grows with the reachable states, not the product space.

``optimal_team_steps(env)``: fewest joint steps (TRIAGE actions count) for the whole team to triage
every victim from the reset state, searching the joint state, so agents blocking each other is exact.
``optimal_team_plan(env)``: one such shortest joint action sequence (the same search, recording parents).
``agent_distances(env, agent)``: the per-agent shortest distances (the agent alone on the map,
victims as obstacles) to enter each region and to triage each victim; the sub-policies' optimum.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from jaxusar.envs.usar import N_ACTIONS, EnvState, USAREnv


class Unreachable(RuntimeError):
    """The goal cannot be reached from the start state."""


class _Codec:
    """Mixed-radix integer <-> batched EnvState (t is not part of the planning state)."""

    def __init__(self, env: USAREnv):
        self.env = env
        self.cell_states = env.height * env.width * 4
        self.n_agents, self.n_victims = env.n_agents, env.n_victims

    def encode(self, pos: np.ndarray, dirs: np.ndarray, triaged: np.ndarray) -> np.ndarray:
        code = np.zeros(len(dirs), np.int64)
        for i in range(self.n_agents):
            cell = (pos[:, i, 0].astype(np.int64) * self.env.width + pos[:, i, 1]) * 4 + dirs[:, i]
            code = code * self.cell_states + cell
        for v in range(self.n_victims):
            code = code * 2 + triaged[:, v]
        return code

    def decode(self, code: np.ndarray):
        code = code.astype(np.int64).copy()
        triaged = np.zeros((len(code), self.n_victims), bool)
        for v in reversed(range(self.n_victims)):
            triaged[:, v] = code % 2
            code //= 2
        pos = np.zeros((len(code), self.n_agents, 2), np.int32)
        dirs = np.zeros((len(code), self.n_agents), np.int32)
        for i in reversed(range(self.n_agents)):
            cell = code % self.cell_states
            code //= self.cell_states
            dirs[:, i] = cell % 4
            pos[:, i, 0] = (cell // 4) // self.env.width
            pos[:, i, 1] = (cell // 4) % self.env.width
        return pos, dirs, triaged


def _joint_actions(n_agents: int) -> np.ndarray:
    """int32[N_ACTIONS ** n_agents, n_agents]: every joint action; row k is the expander's k-th successor."""
    return np.asarray(list(itertools.product(range(N_ACTIONS), repeat=n_agents)), np.int32).reshape(-1, n_agents)


def _expander(env: USAREnv):
    """The jitted successor function of ``env``'s map. Cached by what the step rules read (solid cells,
    victims, agents), not by the env object, so every ``make`` of one map shares one compile."""
    rules = (env._solid.tobytes(), env._solid.shape, env._victim_at.tobytes(), env.n_agents)
    if rules not in _EXPANDERS:
        _EXPANDERS[rules] = _make_expander(env)
    return _EXPANDERS[rules]


_EXPANDERS: dict = {}


def _make_expander(env: USAREnv):
    joint = jnp.asarray(_joint_actions(env.n_agents))

    def successors(pos, dirs, triaged):
        state = EnvState(pos, dirs, triaged, jnp.zeros(pos.shape[:1], jnp.int32))

        def one(s):
            step = lambda a: env.step(None, s, a)[1]
            return jax.vmap(step)(joint)

        nxt = jax.vmap(one)(state)
        return nxt.agent_pos, nxt.agent_dir, nxt.triaged

    return jax.jit(successors)


def _search(env: USAREnv, start: EnvState, is_goal, max_states: int, record: bool = False):
    """Breadth-first search from ``start`` to a state where ``is_goal(pos, dirs, triaged)`` holds.

    Returns ``(depth, plan)``: the fewest joint steps, and with ``record`` one shortest plan int32[depth,
    n_agents] (else None). Recording keeps, per depth, each new state's parent and the joint action that
    first reached it; ties go to the smallest state code and the first joint action, so plans are deterministic.
    """
    codec, expand = _Codec(env), _expander(env)
    frontier = codec.encode(np.asarray(start.agent_pos)[None], np.asarray(start.agent_dir)[None],
                            np.asarray(start.triaged)[None])
    visited = frontier
    depth = 0
    layers = []  # with record: per depth >= 1, (parent index in the previous frontier, joint action index)
    while len(frontier):
        pos, dirs, tri = codec.decode(frontier)
        goal = np.flatnonzero(is_goal(pos, dirs, tri))
        if len(goal):
            return depth, (_backtrack(layers, goal[0], env.n_agents) if record else None)
        pad = 1 << max(int(len(frontier) - 1).bit_length(), 4)  # bucketed sizes: few compiles
        padded = [np.concatenate([x, np.repeat(x[:1], pad - len(x), 0)]) for x in (pos, dirs, tri)]
        npos, ndirs, ntri = (np.asarray(x)[: len(frontier)] for x in expand(*padded))
        codes = codec.encode(npos.reshape(-1, env.n_agents, 2), ndirs.reshape(-1, env.n_agents),
                             ntri.reshape(-1, env.n_victims))
        if record:  # codes is row-major [frontier, joint action]: first = parent * n_joint + action
            codes, first = np.unique(codes, return_index=True)
            new = ~np.isin(codes, visited, assume_unique=True)
            frontier = codes[new]
            layers.append(np.divmod(first[new], N_ACTIONS ** env.n_agents))
        else:
            frontier = np.setdiff1d(np.unique(codes), visited, assume_unique=True)
        visited = np.union1d(visited, frontier)
        depth += 1
        if len(visited) > max_states:
            raise MemoryError(f"planner visited over {max_states} states on {env.layout.name!r}; "
                              "raise max_states or plan on a smaller map")
    raise Unreachable(f"goal unreachable on {env.layout.name!r}")


def _backtrack(layers, index: int, n_agents: int) -> np.ndarray:
    """Joint actions leading to state ``index`` of the last frontier, following recorded parents."""
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
    """An upper bound on the joint states the exact search may visit: (open cells x 4)^agents x 2^victims."""
    return (int((~env.layout.blocked).sum()) * 4) ** env.n_agents * 2 ** env.n_victims


def optimal_team_steps(env: USAREnv, max_states: int = 20_000_000) -> int:
    """Fewest joint primitive steps for the team to triage every victim from the reset state.

    Exact: searches the joint state of all agents, so agents blocking each other is accounted for.
    Ignores the horizon (an optimum above it means the map cannot be solved within it).
    """
    return _bfs(env, env.initial_state(), _all_triaged, max_states)


def optimal_team_plan(env: USAREnv, max_states: int = 20_000_000) -> np.ndarray:
    """One shortest joint plan from the reset state: int32[T, n_agents] actions, T = ``optimal_team_steps(env)``.

    Replaying it through ``env.step`` triages every victim at step T (when T <= horizon). Among the many
    optimal plans it returns a fixed one; agents with slack may spend it on no-op turns or triages.
    """
    return _search(env, env.initial_state(), _all_triaged, max_states, record=True)[1]


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


# -- single-agent distance tables (sub-policy optimum from any start) --------------------------------
@jax.jit
def _single_agent_successors(solid, victim_at):
    """int32[H, W, 4, A, 3] next (row, col, dir) and bool[H, W, 4, A] 'triaged the victim' per action."""
    from jaxusar.envs.usar import apply_actions

    h, w = solid.shape
    rows, cols, dirs, acts = jnp.meshgrid(jnp.arange(h), jnp.arange(w), jnp.arange(4), jnp.arange(N_ACTIONS),
                                          indexing="ij")

    def one(r, c, d, a):
        pos, dr, _, newly = apply_actions(solid, victim_at, jnp.array([[r, c]]), jnp.array([d]),
                                          jnp.zeros((1,), bool), jnp.array([a]))
        return jnp.array([pos[0, 0], pos[0, 1], dr[0]]), newly[0]

    return jax.vmap(jax.vmap(jax.vmap(jax.vmap(one))))(rows, cols, dirs, acts)


def steps_to_goal(solid: np.ndarray, victim_at: np.ndarray, goal_region_mask: np.ndarray | None = None,
                  triage: bool = False) -> np.ndarray:
    """int32[H, W, 4]: fewest steps from every (row, col, dir) for one agent alone to reach its goal.

    Goal: stand in a cell of ``goal_region_mask`` bool[H, W] (0 steps if already there), or, with
    ``triage``, triage the victim marked in ``victim_at`` (its TRIAGE action counts). -1 = unreachable.
    Exact (a fixed point of dist = min_a 1 + dist[next]); the successors are the env's own rules.
    """
    nxt, hit = (np.asarray(x) for x in _single_agent_successors(jnp.asarray(solid), jnp.asarray(victim_at)))
    h, w = solid.shape
    inf = np.iinfo(np.int32).max // 2
    dist = np.full((h, w, 4), inf, np.int64)
    if goal_region_mask is not None:
        dist[goal_region_mask] = 0
    while True:
        after = dist[nxt[..., 0], nxt[..., 1], nxt[..., 2]]  # [H, W, 4, A]
        cost = np.where(hit, 1, 1 + after) if triage else 1 + after
        new = np.minimum(dist, cost.min(-1))
        if np.array_equal(new, dist):
            break
        dist = new
    dist[solid] = -1
    return np.where(dist >= inf, -1, dist).astype(np.int32)
