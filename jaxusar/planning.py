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

from jaxusar.envs.usar import DIR_DELTA, N_ACTIONS, EnvState, USAREnv


class Unreachable(RuntimeError):
    """The goal cannot be reached from the start state."""


class SearchTooLarge(MemoryError):
    """The exact joint search would visit more states than it may (raised before searching when even the
    map's bound on joint states is far past the limit)."""


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
        base = jax.tree.map(lambda x: jnp.broadcast_to(x, (pos.shape[0], *x.shape)), env.initial_state())
        state = base.replace(agent_pos=pos, agent_dir=dirs, triaged=triaged, progress=triaged.astype(jnp.int32))

        def one(s):
            step = lambda a: env.step(None, s, a)[1]
            return jax.vmap(step)(joint)

        nxt = jax.vmap(one)(state)
        return nxt.agent_pos, nxt.agent_dir, nxt.triaged

    return jax.jit(successors)


def _search(env: USAREnv, start: EnvState, is_goal, max_states: int, record: bool = False,
            stats: dict | None = None):
    """Breadth-first search from ``start`` to a state where ``is_goal(pos, dirs, triaged)`` holds.

    Returns ``(depth, plan)``: the fewest joint steps, and with ``record`` one shortest plan int32[depth,
    n_agents] (else None). Recording keeps, per depth, each new state's parent and the joint action that
    first reached it; ties go to the smallest state code and the first joint action, so plans are deterministic.
    ``stats`` (a dict), if given, holds the states visited and the depth reached so far.
    """
    stats = {} if stats is None else stats
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
        stats.update(visited=int(len(visited)), depth=depth)
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
    _check_size(env, max_states)
    return _bfs(env, env.initial_state(), _all_triaged, max_states)


def _check_size(env: USAREnv, max_states: int) -> None:
    bound = joint_states_bound(env)
    if bound > 100 * max_states:
        raise SearchTooLarge(
            f"the exact optimum of {env.layout.name!r} ({env.n_agents} medics, {env.n_victims} victims) needs a joint "
            f"search over up to {bound:.2g} states, past the planner's limit of {max_states:.2g}; training there "
            "measures teams against planning.team_lower_bound instead (planning.team_reference)")


def optimal_team_plan(env: USAREnv, max_states: int = 20_000_000) -> np.ndarray:
    """One shortest joint plan from the reset state: int32[T, n_agents] actions, T = ``optimal_team_steps(env)``.

    Replaying it through ``env.step`` triages every victim at step T (when T <= horizon). Among the many
    optimal plans it returns a fixed one; agents with slack may spend it on no-op turns or triages.
    """
    _check_size(env, max_states)
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
def _fixed_point(dist: np.ndarray, relax) -> np.ndarray:
    """Iterate dist = min(dist, relax(dist)) until nothing changes (shortest paths, Bellman-Ford style)."""
    while True:
        new = np.minimum(dist, relax(dist))
        if np.array_equal(new, dist):
            return dist
        dist = new


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

    def relax(dist):
        after = dist[nxt[..., 0], nxt[..., 1], nxt[..., 2]]  # [H, W, 4, A]
        return (np.where(hit, 1, 1 + after) if triage else 1 + after).min(-1)

    dist = _fixed_point(dist, relax)
    dist[solid] = -1
    return np.where(dist >= inf, -1, dist).astype(np.int32)


# -- a lower bound on the team optimum at any size ------------------------------------------------
def _pose_index(width: int, r, c, d):
    return (np.asarray(r) * width + np.asarray(c)) * 4 + np.asarray(d)


def pose_distances(env: USAREnv, targets: np.ndarray) -> np.ndarray:
    """int64[T, H*W*4]: fewest moves (FORWARD and turns) for one agent alone to stand in pose ``targets[t]``
    (flat (row * W + col) * 4 + dir) from every pose; a large number where it cannot (victims block)."""
    nxt = np.asarray(_single_agent_successors(jnp.asarray(env._solid), jnp.asarray(env._victim_at))[0])
    succ = _pose_index(env.width, nxt[..., 0], nxt[..., 1], nxt[..., 2]).reshape(-1, N_ACTIONS)
    big = np.iinfo(np.int32).max // 4
    dist = np.full((len(targets), succ.shape[0]), big, np.int64)
    dist[np.arange(len(targets)), targets] = 0
    return _fixed_point(dist, lambda d: 1 + d[:, succ].min(-1))


def team_lower_bound(env: USAREnv) -> int:
    """A lower bound on ``optimal_team_steps`` that stays cheap at any map size (its cost grows with the
    victims instead: 2^victims poses tables per medic, 3^victims for the assignment; at most 16 victims).

    Over every assignment of victims to medics, the least makespan (the longest medic's tour) of
    single-agent exact tours: each medic alone on the map (victims block, other medics ignored) triages
    its victims in the best order, turns and TRIAGE actions counted. Exact by dynamic programming: per
    medic over (victims triaged, the pose it triaged the last one from), then over victim subsets for the
    assignment. Only collisions between medics are left out, so the bound is <= the exact optimum (tested
    on every map where the joint search runs) and equal to it for one medic.
    """
    n, v = env.n_agents, env.n_victims
    if v > 16:
        raise ValueError(f"team_lower_bound enumerates victim subsets: {v} victims is more than 16")
    h, w = env.height, env.width
    solid = np.asarray(env._solid)
    poses, victim_of = [], []  # triage poses: an open cell next to a victim, facing it
    for k, (r, c) in enumerate(env.victim_pos):
        for d, (dr, dc) in enumerate(DIR_DELTA):
            pr, pc = r - dr, c - dc  # facing d from (pr, pc) looks at (r, c)
            if 0 <= pr < h and 0 <= pc < w and not solid[pr, pc]:
                poses.append(int(_pose_index(w, pr, pc, d))), victim_of.append(k)
    poses, victim_of = np.asarray(poses), np.asarray(victim_of)
    dist = pose_distances(env, poses)  # [Q, poses]
    inf = np.iinfo(np.int64).max // 4
    full = 1 << v
    costs = np.zeros((n, full), np.int64)
    bit = 1 << victim_of  # [Q]
    between = dist[:, poses].T + 1  # [from q', to q]: move to q, then TRIAGE
    for i, (r, c) in enumerate(env.layout.agent_start):
        f = np.full((full, len(poses)), inf, np.int64)
        f[bit, np.arange(len(poses))] = dist[:, _pose_index(w, r, c, env.start_dir)] + 1
        for s in range(1, full):  # subsets in increasing order: s minus one victim comes before s
            last = (s & bit) != 0
            prev = s & ~bit  # per pose q: the set before its victim
            reach = f[prev[:, None], np.arange(len(poses))[None, :]] + between.T  # [q, q']: end at q after q'
            ok = (prev[:, None] & bit[None, :]) != 0  # q' triaged a victim of the set before
            step = np.where(ok, reach, inf).min(1)
            f[s] = np.where(last, np.minimum(f[s], step), inf)
        costs[i] = f.min(1)
        costs[i, 0] = 0
    best = costs[0].copy()
    for i in range(1, n):  # assignment: best[S] = min over T subset of S of max(best[S \ T], costs[i][T])
        new = np.full(full, inf, np.int64)
        for s in range(full):
            t = s
            while True:
                new[s] = min(new[s], max(best[s & ~t], costs[i][t]))
                if t == 0:
                    break
                t = (t - 1) & s
        best = new
    if best[full - 1] >= inf:
        raise Unreachable(f"some victim of {env.layout.name!r} cannot be triaged")
    return int(best[full - 1])


# the joint-state bound up to which training and `jaxusar demo` run the exact search: two_rooms 1.2e6; past
# it the search takes minutes and gigabytes (benchmarks/README.md, "The exact optimum's limits")
SEARCH_MAX_BOUND = 50_000_000


def team_reference(env: USAREnv, max_states: int = 20_000_000) -> dict:
    """What teams on ``env`` are measured against: ``steps``, the exact optimum where the joint search is
    in reach (``joint_states_bound`` up to ``SEARCH_MAX_BOUND``; ``reference: "optimum"``), else
    ``team_lower_bound`` (``reference: "lower bound"``; a test that takes that many steps is optimal,
    proven by the bound, and longer ones are judged by their gap); and ``lower_bound`` itself, for the
    optimality gap (team steps / lower bound) on every map."""
    bound = team_lower_bound(env)
    if joint_states_bound(env) <= SEARCH_MAX_BOUND:
        try:
            return {"steps": optimal_team_steps(env, max_states), "reference": "optimum", "lower_bound": bound}
        except MemoryError:  # the search passed max_states
            pass
    return {"steps": bound, "reference": "lower bound", "lower_bound": bound}
