"""The BFS planner against a brute-force search over an independent pure-Python copy of the rules.

``RefWorld`` re-implements the DESIGN.md step semantics with tuples and sets (it never calls the
env), so comparing it with ``env.step`` on random transitions is an independent check of the env, and
a plain dict/set BFS over it is an independent check of ``planning``.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxusar import envs, planning
from jaxusar.envs import EnvState

# (d_row, d_col) for EAST, SOUTH, WEST, NORTH, written out again rather than imported.
STEP_DELTA = {0: (0, 1), 1: (1, 0), 2: (0, -1), 3: (-1, 0)}


class RefWorld:
    """The contract's rules on a map given as text; states are (positions, directions, triaged) tuples."""

    def __init__(self, grid: str):
        rows = grid.splitlines()
        self.h, self.w = len(rows), len(rows[0])
        cells = [(r, c, ch) for r, row in enumerate(rows) for c, ch in enumerate(row)]
        self.blocked = {(r, c) for r, c, ch in cells if ch in "#X"}
        self.victims = [(r, c) for r, c, ch in cells if ch == "V"]  # row-major, like the env
        self.starts = [(r, c) for r, c, ch in cells if ch == "A"]

    def step(self, pos, dirs, triaged, actions):
        pos, dirs, triaged = list(pos), list(dirs), list(triaged)
        newly = 0
        for i, a in enumerate(actions):  # index order: later agents see earlier agents' moves
            (r, c), (dr, dc) = pos[i], STEP_DELTA[dirs[i]]
            front = (r + dr, c + dc)
            if a == 0:
                inside = 0 <= front[0] < self.h and 0 <= front[1] < self.w
                if inside and front not in self.blocked and front not in self.victims and front not in pos:
                    pos[i] = front
            elif a == 1:
                dirs[i] = (dirs[i] - 1) % 4
            elif a == 2:
                dirs[i] = (dirs[i] + 1) % 4
            elif a == 3 and front in self.victims and not triaged[self.victims.index(front)]:
                triaged[self.victims.index(front)] = True
                newly += 1
        return (tuple(pos), tuple(dirs), tuple(triaged)), newly

    def shortest(self, starts, start_dir, goal) -> int:
        """Plain BFS over joint states (a set of visited tuples); -1 if ``goal`` is never reached."""
        start = (tuple(starts), (start_dir,) * len(starts), (False,) * len(self.victims))
        joint = list(itertools.product(range(4), repeat=len(starts)))
        seen, frontier, depth = {start}, [start], 0
        while frontier:
            if any(goal(s) for s in frontier):
                return depth
            nxt = []
            for s in frontier:
                for a in joint:
                    s2, _ = self.step(*s, a)
                    if s2 not in seen:
                        seen.add(s2)
                        nxt.append(s2)
            frontier, depth = nxt, depth + 1
        return -1

    def team_optimum(self, start_dir) -> int:
        return self.shortest(self.starts, start_dir, lambda s: all(s[2]))

    def solo_to_triage(self, agent, victim, start_dir) -> int:
        return self.shortest([self.starts[agent]], start_dir, lambda s: s[2][victim])

    def solo_to_cells(self, agent, cells, start_dir) -> int:
        return self.shortest([self.starts[agent]], start_dir, lambda s: s[0][0] in cells)


def regions_for(grid: str) -> str:
    rows = ["".join("#" if ch in "#X" else "R" for ch in row) for row in grid.splitlines()]
    return "R all hall\n---\n" + "\n".join(rows)


def small_env(grid: str, **overrides) -> envs.USAREnv:
    return envs.make(envs.parse_layout(grid, regions_for(grid), "small"), **overrides)


# name: (grid, start direction, what it exercises)
SMALL_MAPS = {
    "open_3x4": ("V..A\n.X..\nA..V", envs.NORTH),
    # one door: the agent behind waits for the one ahead (7 joint steps, per-agent bound 6)
    "door_north": ("V...V\n##.##\n##A##\n##A##", envs.NORTH),
    # the same map upside down: now the agent behind has the lower index, so it is also blocked on
    # the first step (agent 1 has not moved yet when agent 0 acts): 8 joint steps
    "door_south": ("##A##\n##A##\n##.##\nV...V", envs.SOUTH),
    "three_agents": ("A.V\n.A.\nV.A", envs.EAST),
}
EXPECTED_OPTIMUM = {"open_3x4": 4, "door_north": 7, "door_south": 8, "three_agents": 3}


def decoupled_bound(dist: np.ndarray) -> int:
    """min over victim -> agent maps of the max solo time: a lower bound on the team optimum."""
    n_agents, n_victims = dist.shape
    return min(max(dist[f[v], v] for v in range(n_victims))
               for f in itertools.product(range(n_agents), repeat=n_victims))


def best_assignment(dist: np.ndarray) -> int:
    """min over one-victim-per-agent assignments of the max solo time (n_agents == n_victims)."""
    return min(max(dist[a, v] for v, a in enumerate(p)) for p in itertools.permutations(range(len(dist))))


# -- the reference rules against env.step -------------------------------------------------------
CROSS_CHECK_MAPS = {
    "two_rooms": envs.load_layout("two_rooms").to_ascii(),
    "crowded": "AA.V\nA..A\nV.X.",
    "door": SMALL_MAPS["door_north"][0],
    "walls": "A#V.\n.X.A\nV..#",
}


@pytest.mark.parametrize("name", sorted(CROSS_CHECK_MAPS))
def test_reference_rules_match_env_step_on_random_transitions(name):
    grid = CROSS_CHECK_MAPS[name]
    ref = RefWorld(grid)
    env = envs.make("two_rooms") if name == "two_rooms" else small_env(grid)
    rng = np.random.default_rng(sum(map(ord, name)))
    n = 1500
    free = [cell for cell in itertools.product(range(ref.h), range(ref.w))
            if cell not in ref.blocked and cell not in ref.victims]
    # Agents start clustered around a random cell (half the time next to a victim) so that they often
    # block each other and face victims.
    near_victim = [c for c in free if any(abs(c[0] - r) + abs(c[1] - q) == 1 for r, q in ref.victims)]
    pos = []
    for _ in range(n):
        pool = near_victim if rng.random() < 0.5 else free
        anchor = np.array(pool[rng.integers(len(pool))])
        near = sorted(free, key=lambda c: np.abs(np.array(c) - anchor).sum() + rng.random())
        pos.append(near[: env.n_agents])
    pos = np.array(pos, np.int32)
    dirs = rng.integers(0, 4, (n, env.n_agents)).astype(np.int32)
    triaged = rng.random((n, env.n_victims)) < 0.3
    actions = rng.choice(4, (n, env.n_agents), p=[0.55, 0.1, 0.1, 0.25]).astype(np.int32)
    state = EnvState(jnp.asarray(pos), jnp.asarray(dirs), jnp.asarray(triaged), jnp.zeros(n, jnp.int32))
    _, nxt, reward, _, info = jax.jit(jax.vmap(env.step, in_axes=(None, 0, 0)))(None, state, jnp.asarray(actions))
    nxt_pos, nxt_dir, nxt_tri = map(np.asarray, (nxt.agent_pos, nxt.agent_dir, nxt.triaged))
    blocked_moves = triages = 0
    for k in range(n):
        s = (tuple(map(tuple, pos[k].tolist())), tuple(dirs[k].tolist()), tuple(triaged[k].tolist()))
        (rpos, rdir, rtri), newly = ref.step(*s, actions[k].tolist())
        assert (list(map(list, rpos)), list(rdir), list(rtri)) == (
            nxt_pos[k].tolist(), nxt_dir[k].tolist(), nxt_tri[k].tolist()), (s, actions[k])
        assert float(reward[k]) == 100.0 * newly
        blocked_moves += sum(a == 0 and p == q for a, p, q in zip(actions[k], s[0], rpos))
        triages += newly
    assert blocked_moves > 100 and triages > 20  # the sample really exercises blocking and triage


# -- the planner against brute force -------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(SMALL_MAPS))
def test_optimal_team_steps_matches_brute_force(name):
    grid, start_dir = SMALL_MAPS[name]
    optimum = RefWorld(grid).team_optimum(start_dir)
    assert optimum == EXPECTED_OPTIMUM[name]
    assert planning.optimal_team_steps(small_env(grid, start_dir=start_dir)) == optimum


def test_agents_blocking_each_other_make_the_decoupled_bound_inexact():
    for name, optimum in (("door_north", 7), ("door_south", 8)):
        grid, start_dir = SMALL_MAPS[name]
        ref = RefWorld(grid)
        dist = np.array([[ref.solo_to_triage(a, v, start_dir) for v in range(2)] for a in range(2)])
        # the front agent needs 5 steps for either victim, the one behind 6: with one victim each the
        # bound is 6 (5 if the front agent could do both at once), but the door makes the back agent wait
        np.testing.assert_array_equal(np.sort(dist.max(1)), [5, 6])
        assert best_assignment(dist) == 6 and decoupled_bound(dist) == 5
        assert ref.team_optimum(start_dir) == optimum > 6


def test_agent_distances_match_brute_force():
    # Two regions: the top row is a room, the rest a hall; agent 1 is walled off from victim 0.
    grid = "V...V\n##.##\n##A##\n#A###"
    regions = "T top room\nH hall hall\n---\nTTTTT\n##H##\n##H##\n#H###"
    env = envs.make(envs.parse_layout(grid, regions, "split"))
    ref = RefWorld(grid)
    top = {(0, c) for c in range(5)}
    hall = {(1, 2), (2, 2), (3, 1)}
    for agent in range(2):
        got = planning.agent_distances(env, agent)
        want_region = [ref.solo_to_cells(agent, top, envs.NORTH), ref.solo_to_cells(agent, hall, envs.NORTH)]
        want_triage = [ref.solo_to_triage(agent, v, envs.NORTH) for v in range(2)]
        np.testing.assert_array_equal(got["to_region"], want_region)
        np.testing.assert_array_equal(got["to_triage"], want_triage)
    # agent 0: F F (top row) then turn and walk 1 cell and triage: 2 + 1 + 1 + 1 = 5 either way
    np.testing.assert_array_equal(planning.agent_distances(env, 0)["to_triage"], [5, 5])
    np.testing.assert_array_equal(planning.agent_distances(env, 1)["to_region"], [-1, 0])
    np.testing.assert_array_equal(planning.agent_distances(env, 1)["to_triage"], [-1, -1])
    with pytest.raises(ValueError, match="agent 2 out of range 0..1"):
        planning.agent_distances(env, 2)


def test_max_states_guard():
    env = envs.make("two_rooms")  # up to 1.2e6 joint states
    with pytest.raises(MemoryError, match="raise max_states"):  # found while searching
        planning.optimal_team_steps(env, max_states=20_000)
    with pytest.raises(planning.SearchTooLarge, match="up to 1.2e\\+06 states"):  # refused before searching
        planning.optimal_team_steps(env, max_states=50)


# -- two rooms ---------------------------------------------------------------------------------
TOP, HALL, BOTTOM = 0, 1, 2


@pytest.fixture(scope="module")
def two_rooms_distances():
    env = envs.make("two_rooms")
    return [planning.agent_distances(env, a) for a in range(env.n_agents)]


@pytest.fixture(scope="module")
def two_rooms_optimum():
    return planning.optimal_team_steps(envs.make("two_rooms"))


def test_two_rooms_optimum_is_18(two_rooms_optimum):
    assert two_rooms_optimum == 18


def test_two_rooms_agent_distances(two_rooms_distances):
    """Hand-counted (moves + turns (+ 1 TRIAGE)), both medics facing NORTH at the start.

    Top medic, agent 0 at (0,14):
      top room:    14 moves (3 down, 11 left) + 3 turns (west along row 0 to col 5 - (0,4) is a wall -,
                   south to row 3, west into (3,3)); 2 turns cannot do it = 17.
      bottom room: 10 moves ((0,14)->(0,11)->(6,11)->(6,12); row 5 is walled at cols 12-14) + 3 turns
                   (west, south, east) = 13.
      top victim:  19 moves to (1,0) (through (3,3)) + 4 turns (west, south, west, north) + triage = 24.
      bottom victim: 12 moves to (7,13) + 4 turns (west, south, east, south) + triage = 17.
    Bottom medic, agent 1 at (9,0):
      top room:    9 moves (north to row 5, east to col 3, north into (3,3)) + 2 turns = 11.
      bottom room: 14 moves (north to row 7, east to (7,12)) + 1 turn = 15.
      top victim:  14 moves ((9,0)->(5,0)->(5,3)->(0,3)->(0,1)) + 3 turns (east, north, west) + triage = 18.
      bottom victim: 15 moves ((9,0)->(7,0)->(7,13)) + 2 turns (east, south) + triage = 18.
    Both start in the hall-way (0 steps).
    """
    top_medic, bottom_medic = two_rooms_distances
    np.testing.assert_array_equal(top_medic["to_region"], [17, 0, 13])
    np.testing.assert_array_equal(top_medic["to_triage"], [24, 17])
    np.testing.assert_array_equal(bottom_medic["to_region"], [11, 0, 15])
    np.testing.assert_array_equal(bottom_medic["to_triage"], [18, 18])


def test_two_rooms_decoupled_bound_is_exact(two_rooms_distances, two_rooms_optimum):
    dist = np.stack([d["to_triage"] for d in two_rooms_distances])
    # Sec. IV-B: the top medic takes the bottom victim and the bottom medic the top one.
    assert best_assignment(dist) == decoupled_bound(dist) == max(dist[0, 1], dist[1, 0]) == 18
    assert two_rooms_optimum == best_assignment(dist)


def test_two_rooms_hand_plan_finishes_in_18_steps():
    """A concrete 18-step joint plan (the upper bound that matches the planner's optimum)."""
    F, L, R, T = envs.FORWARD, envs.TURN_LEFT, envs.TURN_RIGHT, envs.TRIAGE
    # top medic: west 3, south 6 to (6,11), east 2 to (6,13), south to (7,13), triage (8,13); then idle
    top = [L, F, F, F, L] + [F] * 6 + [L, F, F, R, F, T] + [T]
    # bottom medic: north 4 to (5,0), east 3 to (5,3), north 5 to (0,3), west 2 to (0,1), triage (0,0)
    bottom = [F] * 4 + [R, F, F, F, L] + [F] * 5 + [L, F, F, T]
    assert len(top) == len(bottom) == 18
    env = envs.make("two_rooms")
    step = jax.jit(env.step)
    _, state = env.reset(None)
    rewards = []
    for t, actions in enumerate(zip(top, bottom), start=1):
        _, state, reward, done, info = step(None, state, jnp.asarray(actions, jnp.int32))
        rewards.append(float(reward))
        assert bool(done) == (t == 18)
    assert rewards[16] == 100.0 and rewards[17] == 100.0 and sum(rewards) == 200.0
    np.testing.assert_array_equal(state.agent_pos, [[7, 13], [0, 1]])
    assert bool(info["terminated"]) and int(state.t) == 18


# -- the lower bound ------------------------------------------------------------------------------
def _generated_env(medics, victims, seed, height=9, width=14, rooms=3):
    from jaxusar.envs import mapgen

    return envs.make(mapgen.generated_layout(height, width, rooms, medics, victims, seed)[0])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lower_bound_is_exact_for_one_medic(seed):
    """Alone, a medic's best tour is the optimum: the subset DP must find exactly the BFS answer."""
    env = _generated_env(1, 3, seed)
    assert planning.team_lower_bound(env) == planning.optimal_team_steps(env)


@pytest.mark.parametrize("name", ["two_rooms", "three_rooms"])
def test_lower_bound_never_exceeds_the_exact_optimum(name):
    env = envs.make(name)
    assert planning.team_lower_bound(env) <= planning.optimal_team_steps(env)


@pytest.mark.parametrize("seed", [0, 3])
def test_lower_bound_on_generated_two_medic_maps(seed):
    env = _generated_env(2, 3, seed)
    bound, exact = planning.team_lower_bound(env), planning.optimal_team_steps(env)
    assert 0 < bound <= exact
    # a bound from fewer victims is no larger: dropping victims can only shorten every tour
    fewer = envs.make(env.layout.subset(victims=[0, 1]))
    assert planning.team_lower_bound(fewer) <= bound


def test_lower_bound_runs_where_the_joint_search_cannot():
    env = envs.make("office")  # 4 medics, 6 victims: up to 1.6e15 joint states
    assert planning.joint_states_bound(env) > 1e15
    assert planning.team_lower_bound(env) > 0


def test_team_reference_is_the_optimum_where_the_search_runs_else_the_lower_bound():
    from jaxusar.experiments.train import reference_metrics

    assert planning.team_reference(envs.make("two_rooms")) == {"steps": 18, "reference": "optimum", "lower_bound": 18}
    ref = planning.team_reference(envs.make("four_rooms"))  # 3.2e9 joint states: past the search's limit
    assert ref == {"steps": 25, "reference": "lower bound", "lower_bound": 25}
    # the optimality gap: a trial's shortest solving test over the bound; None where nothing was solved
    got = reference_metrics(ref, {"episodes_to_solved": [40, None, 7], "best_length": np.array([30, 300, 25])})
    assert got["optimality_gap"] == [1.2, None, 1.0] and got["team_lower_bound"] == 25


# -- contract part 2: rubble, engineers, multi-step triage, expiry, drawn victims ----------------------
F, L, R, T = envs.FORWARD, envs.TURN_LEFT, envs.TURN_RIGHT, envs.TRIAGE


def part2_env(grid: str, header: str = "", **overrides) -> envs.USAREnv:
    """A hand map with part 2's characters (r C E ?) and an optional layout header, one region."""
    text = f"{header}\n---\n{grid}" if header else grid
    return envs.make(envs.parse_layout(text, regions_for(grid), "small"), **overrides)


def replay(env, plan, state=None):
    """(state, rewards, dones) after replaying ``plan`` int[T, n_agents] through ``env.step``."""
    step = jax.jit(env.step)
    state = env.initial_state() if state is None else state
    rewards, dones = [], []
    for actions in plan:
        _, state, reward, done, _ = step(None, state, jnp.asarray(actions, jnp.int32))
        rewards.append(float(reward)), dones.append(bool(done))
    return state, np.asarray(rewards), np.asarray(dones)


# The engineer (agent 0) starts 3 cells above the rubble that walls in the victim; the medic (agent 1) can
# face the victim only from the rubble's cell.
RUBBLE_WAIT = "##E#\n##.#\n##.#\n##.#\nA.rV"
# One victim needing 4 TRIAGE actions between two medics facing EAST (agent 1 must turn round first).
SHARED = "A.V.A"
# One medic facing EAST; a critical victim 4 cells west, regular ones north-east and south-east of it.
EXPIRY = ".....V\nC...A.\n.....V"
EXPIRY_SETTINGS = dict(start_dir=envs.EAST, critical_expires=8, horizon=15, step_penalty=-1.0)


@pytest.fixture(scope="module")
def rubble_map():
    env = envs.make("two_rooms_rubble")
    return env, planning.optimal_team_plan(env)


def test_two_rooms_rubble_exact_optimum_replayed(rubble_map):
    """The paper's map with the engineer and the rubble in the bottom room's doorway: still 18 steps (the
    engineer clears the doorway before the top medic gets there), proven by the lower bound (rubble as
    floor) and a plan that does it through env.step."""
    env, plan = rubble_map
    assert env.has_rubble and env.has_engineers and env.n_agents == 3
    assert plan.shape == (18, 3) and planning.optimal_team_steps(env) == 18
    state, rewards, dones = replay(env, plan)
    assert np.all(state.triaged) and rewards.sum() == 200.0
    np.testing.assert_array_equal(dones, np.arange(1, 19) == 18)
    assert not np.asarray(state.rubble)[6:8, 12].all()  # the engineer cleared the doorway
    assert planning.team_lower_bound(env) == 18
    assert planning.team_reference(env) == {"steps": 18, "reference": "optimum", "lower_bound": 18}


def test_rubble_forces_the_engineer_first():
    """Hand count: the engineer walks 3 cells (steps 1-3) and clears the rubble (step 4); the medic turns
    EAST (1), steps to (4, 1) (2), waits (3), enters the cleared cell (4: the engineer acts first) and
    triages (5). Without the rubble the medic would need 4; the bound (rubble as floor) says 4."""
    env = part2_env(RUBBLE_WAIT, start_dir=envs.SOUTH)
    assert env.roles.tolist() == [envs.ENGINEER, envs.MEDIC]
    plan = planning.optimal_team_plan(env)
    assert len(plan) == planning.optimal_team_steps(env) == 5
    assert planning.team_lower_bound(env) == 4
    state, rewards, dones = replay(env, plan[:4])
    assert not bool(state.rubble[4, 2]) and not bool(state.triaged[0])
    assert plan[3, 0] == T and plan[3, 1] == F  # the engineer's tool and the medic's step in one step
    state, rewards, dones = replay(env, plan[4:], state)
    assert bool(state.triaged[0]) and dones[-1]
    # no engineer: the map is refused (the victim cannot be reached)
    with pytest.raises(envs.LayoutError, match="behind rubble"):
        part2_env(RUBBLE_WAIT.replace("E", "#"), start_dir=envs.SOUTH)


@pytest.mark.parametrize("steps, optimum", [(1, 2), (2, 3), (3, 4)])
def test_multi_step_triage_adds_steps(steps, optimum):
    """One medic facing EAST: FORWARD, then one TRIAGE per step the victim needs."""
    env = part2_env("A.V", start_dir=envs.EAST, triage_steps=steps)
    assert planning.optimal_team_steps(env) == optimum
    assert planning.team_lower_bound(env) == optimum  # one medic: the bound is exact


def test_shared_triage_and_the_bound():
    """Medic 0: F, T, T, T; medic 1: L, L, F, T: the 4th TRIAGE action lands at step 4. A bound that charged
    all 4 actions to one medic would say 5 (F + 4 x T) > the optimum; the bound charges ceil(4 / 2)."""
    env = part2_env(SHARED, start_dir=envs.EAST, triage_steps=4)
    assert planning.optimal_team_steps(env) == 4
    state, rewards, _ = replay(env, [[F, L], [T, L], [T, F], [T, T]])
    assert bool(state.triaged[0]) and rewards.sum() == 100.0
    assert planning.team_lower_bound(env) == 3 <= 4


def test_saving_the_critical_victim_beats_triaging_more_regulars():
    """Highest return, not fewest steps. Victims: 0 regular (0, 5), 1 critical (1, 0), 2 regular (2, 5);
    the medic at (1, 4) faces EAST; the critical victim dies at step 8, the horizon is 15, -1 per step.

    Regulars first: F, L, T (victim 0 at step 3), L, L, T (victim 2 at step 6); the critical victim dies
    at 8 and the episode ends: 200 - 8 = 192. Critical first: R, R, F, F, F, T (saved at step 6), then R, F,
    R, F, F, F, T (victim 0 at step 13); victim 2 is out of reach by 15 (it needs (1, 5) facing SOUTH or
    (2, 4) facing EAST: 4 more steps at least), so the episode runs to the horizon: 400 - 15 = 385.
    Saving all three takes 17 steps (the fewest that triage everyone), past the horizon.
    """
    env = part2_env(EXPIRY, **EXPIRY_SETTINGS)
    best = planning.optimal_team_return(env)
    assert best["return"] == 385.0 and best["steps"] == 15
    np.testing.assert_array_equal(best["triaged"], [True, True, False])
    state, rewards, dones = replay(env, best["plan"])
    assert rewards.sum() == 385.0 and dones[-1] and not dones[:-1].any()
    regulars_first = [F, L, T, L, L, T, R, F]
    state, rewards, dones = replay(env, np.asarray(regulars_first)[:, None])
    assert rewards.sum() == 192.0 and dones[-1] and not dones[:-1].any() and bool(state.dead[1])
    assert planning.optimal_team_steps(env) == 17  # ignores the horizon; saves the critical in time
    ref = planning.team_reference(env)
    assert ref == {"steps": 15, "reference": "optimum", "lower_bound": 8, "return": 385.0,
                   "return_reference": "optimum"}
    assert planning.team_return_bound(env) >= 385.0
    # the critical victim gone before anyone can reach it: regulars only, ending when it dies at 5
    late = part2_env(EXPIRY, **{**EXPIRY_SETTINGS, "critical_expires": 5})
    best = planning.optimal_team_return(late)
    assert best["return"] == 200.0 - 6 and best["steps"] == 6


@pytest.mark.parametrize("name", ["rubble_wait", "shared", "expiry", "engineer_and_critical"])
def test_bounds_never_cross_the_exact_optimum(name):
    env = {
        "rubble_wait": lambda: part2_env(RUBBLE_WAIT, start_dir=envs.SOUTH),
        "shared": lambda: part2_env(SHARED, start_dir=envs.EAST, triage_steps=4),
        "expiry": lambda: part2_env(EXPIRY, **EXPIRY_SETTINGS),
        # a medic, an engineer, rubble between the medic and a critical victim needing 2 TRIAGE actions
        "engineer_and_critical": lambda: part2_env("V.r.C\nA.#.E", critical_triage_steps=2, critical_expires=12,
                                                   start_dir=envs.EAST, horizon=30),
    }[name]()
    exact = planning.optimal_team_steps(env)
    assert 0 < planning.team_lower_bound(env) <= exact
    best = planning.optimal_team_return(env)
    assert planning.episode_lower_bound(env) <= best["steps"]
    assert planning.team_return_bound(env) >= best["return"]
    state, rewards, dones = replay(env, best["plan"])
    assert rewards.sum() == pytest.approx(best["return"]) and dones[-1] and not dones[:-1].any()


def brute_force_return(env) -> tuple[float, int]:
    """(highest return, its fewest steps) with no shortcut: every state kept per time step (no state
    reached earlier stands in for a later one), nothing cut, every episode run to its end. The successors
    are the planner's (the env's step), the search around them is independent of it."""
    from jaxusar.planning import search

    codec, expand = search._Codec(env), search._expander(env)
    start = env.complete(env.initial_state())
    worth = np.where(env.victim_kind == envs.CRITICAL, env.critical_reward, env.triage_reward)
    layer, best = codec.encode(codec.of(start)), (-np.inf, 0)
    for t in range(env.horizon + 1):
        s = codec.decode(layer)
        dead = (env.victim_kind == envs.CRITICAL) & ~s.triaged & (t >= (env.critical_expires or np.inf))
        ended = (s.triaged | dead).all(1) | (t >= env.horizon)
        for value in s.triaged[ended] @ worth + env.step_penalty * t:
            best = max(best, (value, -t))
        s = s.take(np.flatnonzero(~ended))
        if not len(s.dirs):
            break
        out = [np.asarray(x) for x in expand(start, s.pos, s.dirs, s.progress, s.rubble, jnp.int32(t))]
        n = len(s.dirs) * 4 ** env.n_agents
        layer = np.unique(codec.encode(search.States(out[0].reshape(n, -1, 2), out[1].reshape(n, -1),
                                                     out[2].reshape(n, -1), None, out[3].reshape(n, -1)
                                                     if out[3].size else np.zeros((n, 0), bool))))
    return float(best[0]), -best[1]


@pytest.mark.parametrize("name", ["rubble_wait", "shared", "expiry", "corridor"])
def test_return_and_steps_searches_match_brute_force(name):
    """The highest-return search (first visits, cuts, rounds, episodes that wait) and the cut fewest-steps
    search against the searches without them. "corridor": the two medics (0, 1), (0, 2) and the engineer
    (2, 2) share a dead-end corridor and can never pass each other, so no one is ever triaged (return 0
    at the horizon), though each alone could; the relaxed bounds cannot see it."""
    env = {
        "rubble_wait": lambda: part2_env(RUBBLE_WAIT, start_dir=envs.SOUTH, horizon=8, step_penalty=-1.0),
        "shared": lambda: part2_env(SHARED, start_dir=envs.EAST, triage_steps=4, horizon=6),
        "expiry": lambda: part2_env(EXPIRY, **EXPIRY_SETTINGS),
        "corridor": lambda: part2_env("#AA.\nVr#.\n.CE.", start_dir=envs.SOUTH, horizon=14, critical_expires=7,
                                      critical_triage_steps=2, triage_steps=2),
    }[name]()
    best = planning.optimal_team_return(env)
    assert (best["return"], best["steps"]) == brute_force_return(env)
    try:
        plain = planning._search(env, env.initial_state(), planning._all_triaged, 1_000_000)[0]
    except planning.Unreachable:
        plain = None
    if plain is None:
        with pytest.raises(planning.Unreachable):
            planning.optimal_team_steps(env)
    else:
        assert planning.optimal_team_steps(env) == plain
    if name == "corridor":
        assert best == {**best, "return": 0.0, "steps": 14} and plain is None
        assert planning.team_return_bound(env) == 400.0 and planning.team_lower_bound(env) == 4


# victims drawn among the '?' cells: one regular, one critical that dies at step 4 (the medic, facing NORTH,
# can triage a top corner in 4 steps, a bottom one in 5: some draws lose the critical victim)
DRAWN = "?...?\n..A..\n?...?"
DRAWN_HEADER = "random_victims: 1 1\ncritical_expires: 4"


def test_clairvoyant_reference_is_deterministic_and_unbeaten_by_scripted_rollouts():
    env = part2_env(DRAWN, DRAWN_HEADER, horizon=20, step_penalty=-1.0)
    ref = planning.clairvoyant_reference(env, n_draws=6, seed=3)
    assert ref == planning.clairvoyant_reference(env, n_draws=6, seed=3)
    assert ref["reference"] == "clairvoyant optimum" and all(ref["exact"]) and ref["n_draws"] == 6
    assert ref["return"] == pytest.approx(np.mean(ref["returns"]))
    keys = jax.random.split(jax.random.PRNGKey(3), 6)
    starts = jax.vmap(env.initial_state)(keys)

    def rollout(key, start, probs):
        def body(carry, key):
            state, total, done = carry
            actions = jax.random.choice(key, 4, (env.n_agents,), p=probs)
            _, state, reward, now_done, _ = env.step(None, state, actions)
            return (state, total + jnp.where(done, 0.0, reward), done | now_done), None

        carry = (start, jnp.float32(0), jnp.bool_(False))
        return jax.lax.scan(body, carry, jax.random.split(key, env.horizon))[0][1]

    scripts = {"uniform": jnp.full(4, 0.25), "triage-heavy": jnp.asarray([0.4, 0.15, 0.15, 0.3])}
    many = jax.jit(jax.vmap(jax.vmap(rollout, in_axes=(0, None, None)), in_axes=(0, 0, None)))
    for name, probs in scripts.items():
        got = np.asarray(many(jax.random.split(jax.random.PRNGKey(7), (6, 256)), starts, probs))  # [draw, run]
        assert np.all(got.max(1) <= np.asarray(ref["returns"]) + 1e-4), name
        assert got.mean() <= ref["return"]
    assert len(set(ref["returns"])) > 1  # the draws differ: where the critical victim is savable, and the steps
    # a draw's optimum is attained: replay the plan of the draw's fixed-victim env on the drawn one
    for k in range(2):
        start = jax.tree.map(lambda x: x[k], starts)
        fixed = planning.fixed_victims(env, start.victim_pos)
        np.testing.assert_array_equal(fixed.victim_kind, env.victim_kind)
        best = planning.optimal_team_return(fixed)
        assert best["return"] == ref["returns"][k] and best["steps"] == ref["draw_steps"][k]
        assert planning.team_return_bound(fixed) >= best["return"]
        _, rewards, dones = replay(env, best["plan"], start)
        assert rewards.sum() == pytest.approx(best["return"]) and dones[-1]
    assert planning.clairvoyant_reference(env, n_draws=6, seed=4) != ref  # another seed, other draws


def test_clairvoyant_reference_on_minimap_is_a_bound():
    env = envs.make("minimap")
    ref = planning.clairvoyant_reference(env, n_draws=2, seed=0)
    assert ref["reference"] == "clairvoyant bound" and ref["exact"] == [False, False]
    most = 6 * env.triage_reward + 2 * env.critical_reward
    assert all(0 < r <= most for r in ref["returns"]) and all(0 < s <= env.horizon for s in ref["draw_lower_bounds"])
    team = planning.team_reference(part2_env(DRAWN, DRAWN_HEADER, horizon=20))
    assert team["reference"] == "clairvoyant optimum" and isinstance(team["steps"], int) and team["n_draws"] == 32


def test_private_names_still_import():
    from jaxusar.planning import _all_triaged, _search, _single_agent_successors  # noqa: F401
