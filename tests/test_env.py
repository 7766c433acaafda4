"""The USAR env's step rules (DESIGN.md contract), invariants under random rollouts, jit/vmap parity."""

from __future__ import annotations

import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from jaxusar import envs
from jaxusar.envs import EAST, FORWARD, NORTH, SOUTH, TRIAGE, TURN_LEFT, TURN_RIGHT, WEST, EnvState

F, L, R, T = FORWARD, TURN_LEFT, TURN_RIGHT, TRIAGE


@functools.lru_cache(maxsize=None)  # one env per map, so its jitted step compiles once
def small_env(grid: str, **overrides) -> envs.USAREnv:
    """An env on an inline map with one region covering every open cell."""
    regions = "\n".join("".join("#" if ch in "#X" else "R" for ch in row) for row in grid.splitlines())
    return envs.make(envs.parse_layout(grid, "R all hall\n---\n" + regions, "small"), **overrides)


def state_of(env, pos, dirs, triaged=None, t=0) -> EnvState:
    """The reset state with the agents, triaged flags and clock given (seen: from the reset starts); a
    leading batch axis on ``dirs`` batches every field."""
    dirs = jnp.asarray(dirs, jnp.int32)
    batch = dirs.shape[:-1]
    triaged = np.zeros((*batch, env.n_victims), bool) if triaged is None else triaged
    base = jax.tree.map(lambda x: jnp.broadcast_to(x, (*batch, *x.shape)), env.initial_state())
    return base.replace(agent_pos=jnp.asarray(pos, jnp.int32), agent_dir=dirs, triaged=jnp.asarray(triaged, bool),
                        progress=jnp.asarray(triaged, jnp.int32), t=jnp.broadcast_to(jnp.asarray(t, jnp.int32), batch))


@functools.lru_cache(maxsize=None)
def jitted_step(env):
    return jax.jit(env.step)


def step(env, state, actions):
    """One jitted step (the rule tests check semantics, not Python-side validation)."""
    return jitted_step(env)(None, state, jnp.asarray(actions, jnp.int32))


def pos_of(state):
    return np.asarray(state.agent_pos).tolist()


def no_entry(env) -> np.ndarray:
    """bool[H, W]: cells no agent may stand on (walls, obstacles, victims), from the public attributes."""
    cells = env.blocked.copy()
    cells[tuple(env.victim_pos.T)] = True
    return cells


# (d_row, d_col) of FORWARD for EAST, SOUTH, WEST, NORTH, written out rather than taken from the env.
DELTA = np.array([[0, 1], [1, 0], [0, -1], [-1, 0]])


# -- moves -------------------------------------------------------------------------------------
OPEN = "V..\n.A.\n..."  # agent at (1, 1), victim out of the way at (0, 0)


@pytest.mark.parametrize("direction, target", [(EAST, [1, 2]), (SOUTH, [2, 1]), (WEST, [1, 0]), (NORTH, [0, 1])])
def test_forward_moves_one_cell_the_way_the_agent_faces(direction, target):
    env = small_env(OPEN)
    _, state, reward, done, info = step(env, state_of(env, [[1, 1]], [direction]), [F])
    assert pos_of(state) == [target]
    assert int(state.agent_dir[0]) == direction  # moving does not turn
    assert int(state.t) == 1 and not bool(state.triaged[0]) and float(reward) == 0.0 and not bool(done)


@pytest.mark.parametrize("cell, direction", [
    ([0, 0], NORTH), ([0, 0], WEST), ([1, 2], SOUTH), ([1, 2], EAST), ([0, 2], NORTH), ([0, 2], EAST),
])
def test_forward_off_the_grid_is_a_no_op(cell, direction):
    env = small_env("A..\n..V")
    _, state, *_ = step(env, state_of(env, [cell], [direction]), [F])
    assert pos_of(state) == [cell]  # no wrap-around, no clipping onto a neighbour
    assert int(state.agent_dir[0]) == direction


def test_walls_and_obstacles_block_open_floor_does_not():
    env = small_env(".#.\nXA.\n..V")
    start = [[1, 1]]
    assert pos_of(step(env, state_of(env, start, [NORTH]), [F])[1]) == start  # wall
    assert pos_of(step(env, state_of(env, start, [WEST]), [F])[1]) == start  # obstacle
    assert pos_of(step(env, state_of(env, start, [EAST]), [F])[1]) == [[1, 2]]
    assert pos_of(step(env, state_of(env, start, [SOUTH]), [F])[1]) == [[2, 1]]


@pytest.mark.parametrize("triaged", [False, True])
def test_victims_block_whether_triaged_or_not(triaged):
    env = small_env("AV.")
    _, state, *_ = step(env, state_of(env, [[0, 0]], [EAST], [triaged]), [F])
    assert pos_of(state) == [[0, 0]]


# -- agents block each other, in index order ----------------------------------------------------
@pytest.mark.parametrize("grid, dirs, actions, expected", [
    # agent 1 ahead of agent 0: agent 0 acts first and still sees agent 1 where it was
    ("AA.\nV..", [EAST, EAST], [F, F], [[0, 0], [0, 2]]),
    # agent 0 ahead of agent 1: agent 1 follows into the cell agent 0 just left
    ("V..\n.AA", [WEST, WEST], [F, F], [[1, 0], [1, 1]]),
    # three in a row moving east: only the front one (agent 2, acting last) moves
    ("AAA.\nV...", [EAST, EAST, EAST], [F, F, F], [[0, 0], [0, 1], [0, 3]]),
    # three in a row moving west: all move, each into the cell the previous agent left
    ("V...\n.AAA", [WEST, WEST, WEST], [F, F, F], [[1, 0], [1, 1], [1, 2]]),
    # both want the same empty cell: the lower index gets it
    ("A.A\nV..", [EAST, WEST], [F, F], [[0, 1], [0, 2]]),
    # head-on: neither can enter the other's cell
    ("AA\nV.", [EAST, WEST], [F, F], [[0, 0], [0, 1]]),
    # the agent ahead only turns: it stays where it is and blocks
    ("V..\n.AA", [EAST, WEST], [L, F], [[1, 1], [1, 2]]),
    # a cell left later in the same step is still occupied when the lower index acts
    ("A..\nA.V", [SOUTH, EAST], [F, F], [[0, 0], [1, 1]]),
    # a cell left earlier in the step is free for the higher index
    ("A..\nA.V", [EAST, NORTH], [F, F], [[0, 1], [0, 0]]),
])
def test_agents_block_each_other_in_index_order(grid, dirs, actions, expected):
    env = small_env(grid)
    state = state_of(env, env.layout.agent_start, dirs)
    _, nxt, *_ = step(env, state, actions)
    assert pos_of(nxt) == expected
    np.testing.assert_array_equal(nxt.agent_dir, [(d + 3) % 4 if a == L else d for d, a in zip(dirs, actions)])


# -- turns -------------------------------------------------------------------------------------
@pytest.mark.parametrize("direction, left, right", [
    (EAST, NORTH, SOUTH), (SOUTH, EAST, WEST), (WEST, SOUTH, NORTH), (NORTH, WEST, EAST),
])
def test_turns(direction, left, right):
    env = small_env(OPEN)
    for action, want in ((L, left), (R, right), (F, direction), (T, direction)):
        _, state, *_ = step(env, state_of(env, [[1, 1]], [direction]), [action])
        assert int(state.agent_dir[0]) == want, envs.ACTION_NAMES[action]
        if action != F:
            assert pos_of(state) == [[1, 1]]  # turning and triage never move


def test_four_left_turns_or_four_right_turns_come_back():
    env = small_env(OPEN)
    state = state_of(env, [[1, 1]], [SOUTH])
    seen = []
    for _ in range(4):
        _, state, *_ = step(env, state, [R])
        seen.append(int(state.agent_dir[0]))
    assert seen == [WEST, NORTH, EAST, SOUTH]


# -- triage ------------------------------------------------------------------------------------
@pytest.mark.parametrize("cell, direction, hit", [
    ([0, 1], WEST, True), ([1, 0], NORTH, True),  # facing the victim at (0, 0)
    ([0, 1], EAST, False), ([0, 1], SOUTH, False), ([0, 1], NORTH, False),  # next to it, facing away
    ([1, 0], SOUTH, False), ([1, 0], WEST, False),
    ([1, 1], NORTH, False), ([1, 1], WEST, False),  # diagonal
    ([0, 2], WEST, False),  # two cells away, facing it
])
def test_triage_only_when_facing_the_victim(cell, direction, hit):
    env = small_env("V..\n.A.\n...", horizon=10)
    obs, state, reward, done, info = step(env, state_of(env, [cell], [direction]), [T])
    assert bool(state.triaged[0]) == hit
    assert bool(info["newly_triaged"][0]) == hit
    assert float(reward) == (100.0 if hit else 0.0)
    assert bool(done) == hit and bool(info["terminated"]) == hit
    assert pos_of(state) == [cell] and int(state.agent_dir[0]) == direction
    assert float(obs[-1]) == float(hit)  # the triaged flag is in the observation


def test_triage_only_the_victim_in_front():
    env = small_env("V.V\nAA.\n...")
    # agent 0 at (1,0) faces victim 0 at (0,0); victim 1 at (0,2) is diagonal to agent 1 at (1,1)
    _, state, reward, _, info = step(env, state_of(env, [[1, 0], [1, 1]], [NORTH, EAST]), [T, T])
    np.testing.assert_array_equal(state.triaged, [True, False])
    np.testing.assert_array_equal(info["newly_triaged"], [True, False])
    assert float(reward) == 100.0


def test_triage_is_counted_once():
    env = small_env("V..\nA.V\n...")  # two victims, so one triage does not end the episode
    state = state_of(env, [[1, 0]], [NORTH])
    _, state, reward, done, info = step(env, state, [T])
    assert float(reward) == 100.0 and bool(state.triaged[0]) and not bool(done)
    for _ in range(2):  # triaging it again: no reward, still triaged
        _, state, reward, done, info = step(env, state, [T])
        assert float(reward) == 0.0 and not bool(info["newly_triaged"].any())
        np.testing.assert_array_equal(state.triaged, [True, False])


def test_two_agents_triaging_one_victim_in_the_same_step_count_once():
    env = small_env("AVA\n..V")
    _, state, reward, done, info = step(env, state_of(env, [[0, 0], [0, 2]], [EAST, WEST]), [T, T])
    assert float(reward) == 100.0
    np.testing.assert_array_equal(info["newly_triaged"], [True, False])
    np.testing.assert_array_equal(state.triaged, [True, False])


def test_two_victims_triaged_in_one_step_pay_twice_and_end_the_episode():
    env = small_env("AVA\n..V")
    # agent 0 faces victim 0 at (0,1); agent 1 at (0,2) faces victim 1 at (1,2)
    _, state, reward, done, info = step(env, state_of(env, [[0, 0], [0, 2]], [EAST, SOUTH]), [T, T])
    assert float(reward) == 200.0
    np.testing.assert_array_equal(info["newly_triaged"], [True, True])
    assert bool(done) and bool(info["terminated"]) and not bool(info["truncated"])


# -- reward and done ---------------------------------------------------------------------------
def test_reward_is_triage_reward_times_newly_triaged_plus_step_penalty():
    env = small_env("AVA\n..V", triage_reward=7.5, step_penalty=-0.25)
    state = state_of(env, [[0, 0], [0, 2]], [EAST, SOUTH])
    # turn away and back, bump into victim 0 while agent 1 triages victim 1, then agent 0 triages
    for actions, want in (([L, L], -0.25), ([R, R], -0.25), ([F, T], 7.25), ([T, T], 7.25), ([T, T], -0.25)):
        _, state, reward, *_ = step(env, state, actions)
        assert reward.dtype == jnp.float32 and reward.shape == ()
        assert float(reward) == want, actions
    state = state_of(env, [[0, 0], [0, 2]], [EAST, SOUTH])
    assert float(step(env, state, [T, T])[2]) == 2 * 7.5 - 0.25


def test_done_at_the_horizon_and_not_before():
    env = small_env("A.V", horizon=3)
    _, state = env.reset(None)
    for t in (1, 2, 3):
        _, state, _, done, info = step(env, state, [L])
        assert int(state.t) == t
        assert bool(done) == (t == 3) and bool(info["truncated"]) == (t == 3)
        assert not bool(info["terminated"])
        assert done.dtype == jnp.bool_


def test_done_when_all_victims_are_triaged():
    env = small_env("A.V\n...", horizon=50)
    state = state_of(env, [[0, 1]], [EAST])
    _, state, reward, done, info = step(env, state, [T])
    assert bool(done) and bool(info["terminated"]) and not bool(info["truncated"])
    assert int(state.t) == 1


def test_triage_on_the_last_step_is_terminated_not_truncated():
    env = small_env("A.V\n...", horizon=2)
    state = state_of(env, [[0, 1]], [EAST], t=1)
    _, state, reward, done, info = step(env, state, [T])
    assert bool(done) and bool(info["terminated"]) and not bool(info["truncated"]) and float(reward) == 100.0


def test_step_never_resets():
    env = small_env("A.V\n...", horizon=2)
    state = state_of(env, [[0, 0]], [SOUTH], t=2)  # already at the horizon
    _, state, reward, done, _ = step(env, state, [F])
    assert int(state.t) == 3 and bool(done)
    assert pos_of(state) == [[1, 0]]  # actions still act
    state = state_of(env, [[0, 1]], [EAST], [True])  # already all triaged
    _, state, reward, done, _ = step(env, state, [T])
    assert bool(done) and float(reward) == 0.0 and bool(state.triaged[0])


def test_reset_is_the_fixed_start():
    env = envs.make("two_rooms", start_dir="EAST")
    obs, state = env.reset(jax.random.key(3))
    obs2, state2 = env.reset(jax.random.key(4))
    np.testing.assert_array_equal(obs, obs2)
    assert state.agent_pos.dtype == jnp.int32 and state.agent_pos.shape == (2, 2)
    assert state.agent_dir.dtype == jnp.int32 and state.agent_dir.shape == (2,)
    assert state.triaged.dtype == jnp.bool_ and state.triaged.shape == (2,)
    assert state.t.dtype == jnp.int32 and state.t.shape == ()
    np.testing.assert_array_equal(state.agent_pos, [[0, 14], [9, 0]])
    np.testing.assert_array_equal(state.agent_dir, [EAST, EAST])
    assert int(state.t) == 0 and not bool(state.triaged.any())


def test_observation_layout():
    env = envs.make("two_rooms")
    obs, state = env.reset(None)
    assert obs.shape == (60,) and obs.dtype == jnp.float32
    hot = np.flatnonzero(np.asarray(obs)).tolist()
    # agent 0: row 0, col 14, NORTH; agent 1 (offset 29): row 9, col 0, NORTH; no victim triaged
    assert hot == [0, 10 + 14, 25 + NORTH, 29 + 9, 29 + 10 + 0, 29 + 25 + NORTH]
    moved = state_of(env, [[3, 3], [7, 12]], [EAST, SOUTH], [False, True])
    hot = np.flatnonzero(np.asarray(env.observe(moved))).tolist()
    assert hot == [3, 10 + 3, 25 + EAST, 29 + 7, 29 + 10 + 12, 29 + 25 + SOUTH, 59]
    obs, nxt, *_ = step(env, moved, [L, F])
    np.testing.assert_array_equal(obs, env.observe(nxt))


# -- actions from Python -----------------------------------------------------------------------
@pytest.mark.parametrize("actions, error, message", [
    ([4, 0], ValueError, "actions must be in 0..3"),
    ([0, -1], ValueError, "got [0, -1]"),
    (np.array([0, 9], np.int32), ValueError, "actions must be in 0..3"),
    (jnp.array([7, 0], jnp.int32), ValueError, "got [7, 0]"),
    ([0, 1, 2], ValueError, "actions must have shape (2,) (one per agent), got (3,)"),
    (0, ValueError, "actions must have shape (2,)"),
    ([[0, 1]], ValueError, "got (1, 2)"),
    ([0.0, 1.0], TypeError, "actions must be integers 0..3, got dtype float64"),
])
def test_bad_actions_from_python_raise(actions, error, message):
    env = envs.make("two_rooms")
    _, state = env.reset(None)
    with pytest.raises(error, match=re.escape(message)):
        env.step(None, state, actions)


def test_python_actions_of_any_integer_type_work_eagerly():
    env = envs.make("two_rooms")
    _, state = env.reset(None)
    for actions in ([1, 2], np.array([1, 2], np.int8), jnp.array([1, 2])):
        _, nxt, *_ = env.step(None, state, actions)
        np.testing.assert_array_equal(nxt.agent_dir, [WEST, EAST])


def test_out_of_range_actions_inside_jit_are_no_ops():
    env = envs.make("two_rooms")
    _, state = env.reset(None)
    _, nxt, reward, _, _ = step(env, state, [7, -2])
    np.testing.assert_array_equal(nxt.agent_pos, state.agent_pos)
    np.testing.assert_array_equal(nxt.agent_dir, state.agent_dir)
    assert int(nxt.t) == 1 and float(reward) == 0.0


# -- random rollouts: invariants (hypothesis) ----------------------------------------------------
CROWDED = "AA.V\nA..A\nV.X."  # 4 agents on 9 open cells: they collide most steps
ROLLOUT_STEPS = 30
INVARIANT_ENVS = {
    "two_rooms": envs.make("two_rooms", horizon=25),
    "crowded": small_env(CROWDED, horizon=20, triage_reward=7.0, step_penalty=-0.5),
}


def _rollout(env, state, actions):
    def body(s, a):
        obs, s2, reward, done, info = env.step(None, s, a)
        return s2, (s2, obs, reward, done, info["newly_triaged"], info["terminated"], info["truncated"])

    return jax.lax.scan(body, state, actions)[1]


ROLLOUTS = {name: jax.jit(functools.partial(_rollout, env)) for name, env in INVARIANT_ENVS.items()}


@st.composite
def starts_and_actions(draw, name):
    """A valid state (agents on distinct open non-victim cells) and ROLLOUT_STEPS joint actions."""
    env = INVARIANT_ENVS[name]
    free = np.argwhere(~no_entry(env)).tolist()
    cells = draw(st.permutations(free))[: env.n_agents]
    dirs = draw(st.lists(st.integers(0, 3), min_size=env.n_agents, max_size=env.n_agents))
    triaged = draw(st.lists(st.booleans(), min_size=env.n_victims, max_size=env.n_victims))
    t = draw(st.integers(0, env.horizon))
    actions = draw(hnp.arrays(np.int32, (ROLLOUT_STEPS, env.n_agents), elements=st.integers(0, 3)))
    return state_of(env, cells, dirs, triaged, t), actions


def expected_obs(env, pos, dirs, triaged):
    """float32[..., obs_dim] in numpy: per agent one-hot(row), one-hot(col), one-hot(dir); triaged flags."""
    parts = []
    for i in range(env.n_agents):
        parts += [np.eye(env.height)[pos[..., i, 0]], np.eye(env.width)[pos[..., i, 1]], np.eye(4)[dirs[..., i]]]
    return np.concatenate(parts + [triaged.astype(float)], -1).astype(np.float32)


def check_invariants(env, start, actions, out):
    states, obs, reward, done, newly, terminated, truncated = jax.tree.map(np.asarray, out)
    pos, dirs, tri, t = states.agent_pos, states.agent_dir, states.triaged, states.t
    prev_pos = np.concatenate([np.asarray(start.agent_pos)[None], pos[:-1]])
    prev_dir = np.concatenate([np.asarray(start.agent_dir)[None], dirs[:-1]])
    prev_tri = np.concatenate([np.asarray(start.triaged)[None], tri[:-1]])
    h, w = env.height, env.width
    # no agent outside the grid, on a blocked or victim cell, or sharing a cell
    assert ((pos >= 0) & (pos < [h, w])).all()
    assert not no_entry(env)[pos[..., 0], pos[..., 1]].any()
    flat = pos[..., 0] * w + pos[..., 1]
    assert all(len(set(row)) == env.n_agents for row in flat.tolist())
    # triaged never reverts; reward = triage_reward x newly triaged + step_penalty
    assert (tri >= prev_tri).all()
    np.testing.assert_array_equal(newly, tri & ~prev_tri)
    np.testing.assert_allclose(reward, env.triage_reward * newly.sum(-1) + env.step_penalty, rtol=1e-6)
    # time, done and its two reasons
    np.testing.assert_array_equal(t, int(start.t) + 1 + np.arange(len(actions)))
    np.testing.assert_array_equal(terminated, tri.all(-1))
    np.testing.assert_array_equal(done, tri.all(-1) | (t >= env.horizon))
    np.testing.assert_array_equal(truncated, done & ~tri.all(-1))
    # each agent moves at most one cell, only on FORWARD, only the way it faces; turns follow the rule
    moved = (pos != prev_pos).any(-1)
    assert not (moved & (actions != F)).any()
    np.testing.assert_array_equal(pos[moved], prev_pos[moved] + DELTA[prev_dir[moved]])
    want_dir = np.where(actions == L, (prev_dir + 3) % 4, np.where(actions == R, (prev_dir + 1) % 4, prev_dir))
    np.testing.assert_array_equal(dirs, want_dir)
    # a victim is newly triaged exactly when some agent faces it (as it stood before acting) with TRIAGE
    # and it was not triaged before; agents do not move on TRIAGE, so the facing is the step's start
    front = prev_pos + DELTA[prev_dir]  # [steps, agents, 2]
    facing = (front[:, :, None, :] == env.victim_pos[None, None]).all(-1)  # [steps, agents, victims]
    triaging = (facing & (actions == T)[..., None]).any(1)
    np.testing.assert_array_equal(newly, triaging & ~prev_tri)
    # the observation is the documented encoding of the new state
    np.testing.assert_array_equal(obs, expected_obs(env, pos, dirs, tri))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(starts_and_actions("two_rooms"))
def test_invariants_random_rollouts_two_rooms(example):
    start, actions = example
    env = INVARIANT_ENVS["two_rooms"]
    check_invariants(env, start, actions, ROLLOUTS["two_rooms"](start, jnp.asarray(actions)))


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(starts_and_actions("crowded"))
def test_invariants_random_rollouts_crowded(example):
    start, actions = example
    env = INVARIANT_ENVS["crowded"]
    check_invariants(env, start, actions, ROLLOUTS["crowded"](start, jnp.asarray(actions)))


def test_crowded_rollouts_do_collide_and_triage():
    """Guards the invariant tests against vacuity: on the crowded map, random play blocks and triages."""
    env = INVARIANT_ENVS["crowded"]
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 4, (ROLLOUT_STEPS, env.n_agents)).astype(np.int32)
    _, start = env.reset(None)
    states, *_ , newly, _, _ = ROLLOUTS["crowded"](start, jnp.asarray(actions))
    pos = np.asarray(states.agent_pos)
    prev = np.concatenate([np.asarray(start.agent_pos)[None], pos[:-1]])
    blocked_forward = (actions == F) & (pos == prev).all(-1)
    assert blocked_forward.sum() >= 10
    assert np.asarray(newly).any()


# -- jit vs eager, vmap vs per-env ---------------------------------------------------------------
def random_states(env, n, rng):
    """n valid states: agents on distinct open non-victim cells, random directions, flags and times."""
    free = np.argwhere(~no_entry(env))
    pos = np.stack([free[rng.permutation(len(free))[: env.n_agents]] for _ in range(n)])
    return state_of(env, pos, rng.integers(0, 4, (n, env.n_agents)), rng.random((n, env.n_victims)) < 0.5,
                    rng.integers(0, env.horizon + 1, n))


@pytest.mark.parametrize("name", ["two_rooms", "crowded"])
def test_jit_matches_eager(name):
    env = INVARIANT_ENVS[name]
    rng = np.random.default_rng(1)
    state = jax.tree.map(lambda x: x[0], random_states(env, 1, rng))
    eager_state, jit_state = state, state
    for _ in range(12):
        actions = rng.integers(0, 4, env.n_agents).astype(np.int32)
        eager = env.step(None, eager_state, actions)
        jitted = step(env, jit_state, actions)
        jax.tree.map(np.testing.assert_array_equal, eager, jitted)
        eager_state, jit_state = eager[1], jitted[1]


@pytest.mark.parametrize("name", ["two_rooms", "crowded"])
def test_vmap_matches_per_env(name):
    env = INVARIANT_ENVS[name]
    rng = np.random.default_rng(2)
    n = 64
    states = random_states(env, n, rng)
    actions = jnp.asarray(rng.integers(0, 4, (n, env.n_agents)), jnp.int32)
    batched = jax.jit(jax.vmap(env.step, in_axes=(None, 0, 0)))(None, states, actions)
    for i in range(n):
        one = step(env, jax.tree.map(lambda x: x[i], states), actions[i])
        jax.tree.map(lambda b, o: np.testing.assert_array_equal(b[i], o), batched, one)
    assert int(batched[4]["newly_triaged"].sum()) > 0 or name == "two_rooms"  # triage happened
