"""The paper's method: options from the graph, pseudo-reward sub-tasks, the SMDP coordinator."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxusar import config, envs, planning
from jaxusar.algos import coordinator as coord
from jaxusar.algos import defaults as algos_defaults
from jaxusar.algos import subpolicies as sp
from jaxusar.algos.options import (CLEAR, NAVIGATE, TRIAGE, Rubble, doorway_rubble_regions, method_env, next_hop,
                                   options_from_graph, waiting_cells)
from jaxusar.config import ConfigError
from jaxusar.experiments import hierarchical
from jaxusar.experiments.hierarchical import auto_option_timeout

THREE_ROOMS = """
V..#...#..V
...#...#...
.......#...
...#.......
...#..A#...
###########
.....A....V
"""
THREE_ROOMS_REGIONS = """
L left_room room
H hall hall
R right_room room
S south_room room
---
LLL#HHH#RRR
LLL#HHH#RRR
LLLHHHH#RRR
LLL#HHHHRRR
LLL#HHH#RRR
###########
SSSSSSSSSSS
"""


@pytest.fixture(scope="module")
def two_rooms():
    env = envs.make("two_rooms", horizon=300)
    return env, options_from_graph(env.graph)


def test_two_rooms_options_are_table_one(two_rooms):
    _, opts = two_rooms
    assert opts.names == ("NAVIGATE-TO-TOP-ROOM", "NAVIGATE-TO-BOTTOM-ROOM", "TRIAGE-TOP-VICTIM",
                          "TRIAGE-BOTTOM-VICTIM")
    np.testing.assert_array_equal(opts.kind, [NAVIGATE, NAVIGATE, TRIAGE, TRIAGE])
    np.testing.assert_array_equal(opts.victim, [-1, -1, 0, 1])


def test_initiation_and_termination_from_regions(two_rooms):
    env, opts = two_rooms
    top, hall, bottom = (env.graph.index(n) for n in ("top_room", "hall_way", "bottom_room"))
    none = jnp.array([False, False])
    np.testing.assert_array_equal(opts.can_initiate(hall, none), [True, True, False, False])
    np.testing.assert_array_equal(opts.can_initiate(top, none), [False, False, True, False])
    np.testing.assert_array_equal(opts.can_initiate(bottom, none), [False, False, False, True])
    np.testing.assert_array_equal(opts.can_initiate(top, jnp.array([True, False])), [False] * 4)  # triaged
    assert bool(opts.terminated(0, top, none)) and not bool(opts.terminated(0, hall, none))
    assert bool(opts.terminated(3, hall, jnp.array([False, True])))
    assert not bool(opts.terminated(2, top, jnp.array([False, True])))


def test_options_on_a_three_room_map_need_no_new_code():
    layout = envs.parse_layout(THREE_ROOMS, THREE_ROOMS_REGIONS, "three_rooms")
    env = envs.make(layout)
    opts = options_from_graph(env.graph)
    assert opts.names == ("NAVIGATE-TO-LEFT-ROOM", "NAVIGATE-TO-RIGHT-ROOM", "NAVIGATE-TO-SOUTH-ROOM",
                          "TRIAGE-LEFT-VICTIM", "TRIAGE-RIGHT-VICTIM", "TRIAGE-SOUTH-VICTIM")
    left, hall, right, south = range(4)
    none = jnp.zeros(3, bool)
    # the south room touches no other region: nothing navigates there, the hall reaches left and right
    np.testing.assert_array_equal(opts.can_initiate(hall, none), [True, True, False, False, False, False])
    np.testing.assert_array_equal(opts.can_initiate(south, none), [False, False, False, False, False, True])
    np.testing.assert_array_equal(opts.can_initiate(left, none), [False] * 3 + [True, False, False])
    tasks = sp.make_tasks(env, opts)
    # agent 0 starts in the hall (adjacent to left and right), agent 1 in the south room (adjacent to none)
    assert [t.name for t in tasks] == ["agent0:NAVIGATE-TO-LEFT-ROOM", "agent0:NAVIGATE-TO-RIGHT-ROOM",
                                       "TRIAGE-LEFT-VICTIM", "TRIAGE-RIGHT-VICTIM", "TRIAGE-SOUTH-VICTIM"]


def test_pseudo_reward_env(two_rooms):
    env, opts = two_rooms
    tasks = sp.make_tasks(env, opts)
    params = sp.task_params(env, tasks, 0.99, {"TRIAGE-BOTTOM-VICTIM": 0.9})
    senv = sp.SubtaskEnv(env, horizon=50)
    k = [t.name for t in tasks].index("agent1:NAVIGATE-TO-TOP-ROOM")
    p = jax.tree.map(lambda x: jnp.asarray(x[k]), params)
    assert not params.solid[k][8, 13] and not params.solid[k][0, 0]  # victims removed for navigation
    obs, s = senv.reset_test(jax.random.PRNGKey(0), p)
    assert s.agent_pos.tolist() == [[9, 0]] and obs.shape == (senv.obs_dim,)
    assert int(senv.optimal_steps_from(s, p)) == 11 == planning.agent_distances(env, 1)["to_region"][0]
    step = jax.jit(senv.step)
    plan = [0] * 4 + [2] + [0] * 3 + [1] + [0, 0]  # up 4, turn east, 3 east, turn north, 2 up to (3,3)
    rewards = []
    for a in plan:
        obs, s, r, done, info = step(None, s, jnp.array([a]), p)
        rewards.append(float(r))
    assert s.agent_pos.tolist() == [[3, 3]] and bool(done) and bool(info["terminated"])
    assert rewards == [-1.0] * 10 + [99.0]
    assert float(info["gamma"]) == pytest.approx(0.99)
    kb = [t.name for t in tasks].index("TRIAGE-BOTTOM-VICTIM")
    assert float(params.gamma[kb]) == pytest.approx(0.9)
    assert params.solid[kb][8, 13] and not params.solid[kb][0, 0]  # only its own victim is kept
    with pytest.raises(ConfigError, match="TRIAGE-NOWHERE.*does not have.*task_gamma={}"):
        sp.task_params(env, tasks, 0.99, {"TRIAGE-NOWHERE": 0.5})


def test_pseudo_env_times_out_with_step_penalty(two_rooms):
    env, opts = two_rooms
    tasks = sp.make_tasks(env, opts)
    params = sp.task_params(env, tasks, 0.99, {})
    senv = sp.SubtaskEnv(env, horizon=3)
    p = jax.tree.map(lambda x: jnp.asarray(x[0]), params)
    _, s = senv.reset_test(None if False else jax.random.PRNGKey(0), p)
    for t in range(3):
        _, s, r, done, info = senv.step(None, s, jnp.array([1]), p)  # turning forever
        assert float(r) == -1.0 and bool(done) == (t == 2) and not bool(info["terminated"])


def _macro(env, opts, invalid_penalty=-100.0, option_timeout=1000):
    """A macro env whose 'sub-policies' are scripted: always FORWARD (enough for these checks)."""
    policy_for = np.array([[0, 1, 2, 3], [0, 1, 2, 3]])
    return coord.MacroEnv(env, opts, policy_for, subpolicy_act=lambda p, obs: jnp.array([0]),
                          observe=sp.SubtaskEnv(env, env.horizon).observe, gamma=0.9,
                          invalid_penalty=invalid_penalty, option_timeout=option_timeout)


def test_macro_env_validity_and_invalid_choice(two_rooms):
    env, opts = two_rooms
    macro = _macro(env, opts)
    obs, s = macro.reset(None)
    # both medics start in the hall-way: only the navigation options are available to each
    assert np.flatnonzero(np.asarray(macro.valid_joint(obs))).tolist() == [0, 1, 4, 5]
    p = coord.CoordinatorParams(subpolicy=jnp.zeros((4, 1)))
    obs2, s2, r, done, info = macro.step(None, s, jnp.array([2 * 4 + 0]), p)  # TRIAGE-TOP from the hall
    assert float(r) == -100.0 and not bool(info["valid"]) and int(info["steps"]) == 1
    assert int(s2.t) == 1 and s2.agent_pos.tolist() == s.agent_pos.tolist() and not bool(done)


def test_an_invalid_choice_runs_no_subpolicy_step_even_beside_valid_ones(two_rooms):
    """Under vmap, lax.cond computes both branches: an invalid lane must not run its (wrong) sub-policy to
    the timeout while the batch waits. Counted: sub-policy calls of a batch whose choices are all invalid."""
    env, opts = two_rooms
    calls = []

    def act(p, obs):
        jax.debug.callback(lambda: calls.append(1))
        return jnp.array([0])

    macro = coord.MacroEnv(env, opts, np.array([[0, 1, 2, 3], [0, 1, 2, 3]]), subpolicy_act=act,
                           observe=sp.SubtaskEnv(env, env.horizon).observe, gamma=0.9, invalid_penalty=-100.0,
                           option_timeout=7)
    _, s = macro.reset(None)
    p = coord.CoordinatorParams(subpolicy=jnp.zeros((4, 1)))
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), s)
    step = jax.jit(jax.vmap(macro.step, in_axes=(None, 0, 0, None)))
    _, s2, r, _, info = step(None, batch, jnp.array([[2 * 4 + 0], [3 * 4 + 3]]), p)  # TRIAGE from the hall
    jax.effects_barrier()
    assert not info["valid"].any() and r.tolist() == [-100.0, -100.0] and s2.t.tolist() == [1, 1]
    assert calls == []
    # beside a valid lane, the invalid one still stands still; the valid one walks until its timeout
    _, s2, r, _, info = step(None, batch, jnp.array([[2 * 4 + 0], [0]]), p)
    jax.effects_barrier()
    assert info["valid"].tolist() == [False, True] and info["steps"].tolist() == [1, 7] and s2.t.tolist() == [1, 7]
    assert len(calls) == 7 * env.n_agents  # the valid lane's 7 steps; no call runs for the invalid lane alone


def test_macro_step_runs_until_the_first_option_terminates(two_rooms):
    env, opts = two_rooms
    macro = _macro(env, opts)
    obs, s = macro.reset(None)
    p = coord.CoordinatorParams(subpolicy=jnp.zeros((4, 1)))
    # both "navigate" by walking north: the bottom medic (9,0) stops at the wall below (4,0), the top
    # medic cannot move; nothing terminates, so the option runs to the horizon
    obs, s2, r, done, info = macro.step(None, s, jnp.array([0 * 4 + 0]), p)
    assert bool(done) and int(info["steps"]) == env.horizon and s2.agent_pos.tolist() == [[0, 14], [5, 0]]
    # ... unless it times out first
    obs, s3, r, done, info = _macro(env, opts, option_timeout=7).step(None, s, jnp.array([0]), p)
    assert not bool(done) and int(info["steps"]) == 7 and int(s3.t) == 7


def _forward_macro(grid: str, region_rows: str, option_timeout: int, **kw):
    """Rooms a (west) and b (east) joined by a hall; medic 0 bound east (NAVIGATE-TO-B-ROOM), medic 1 west,
    scripted sub-policies that always go FORWARD."""
    regions = "A a_room room\nB b_room room\nC hall hall\n---\n" + region_rows
    env = envs.make(envs.parse_layout(grid, regions, "hall"))
    opts = options_from_graph(env.graph, "adjacent")
    macro = coord.MacroEnv(env, opts, np.zeros((2, opts.n), np.int32), subpolicy_act=lambda p, obs: jnp.array([0]),
                           observe=sp.SubtaskEnv(env, env.horizon).observe, gamma=0.9, invalid_penalty=-100.0,
                           option_timeout=option_timeout, factored=True, **kw)
    options = jnp.array([opts.names.index("NAVIGATE-TO-B-ROOM"), opts.names.index("NAVIGATE-TO-A-ROOM")])
    return macro, options, coord.CoordinatorParams(subpolicy=jnp.zeros((1, 1)))


def _corridor_macro(**kw):
    """The hall a one-wide corridor."""
    return _forward_macro("V.#######.V\n....AA.....", "AA#######BB\nAACCCCCCCBB", 7, **kw)


@pytest.mark.parametrize("patience", [0, 1, 3])
def test_options_end_when_medics_block_each_other_head_on(patience):
    """Head-on in the corridor, neither medic can move: the options run to the timeout (7) unless
    block_patience ends them after that many blocked steps; a medic following another is not blocked."""
    macro, options, p = _corridor_macro(block_patience=patience)
    _, s = macro.reset(None)
    s = s.env
    head_on = s.replace(agent_dir=jnp.array([0, 2]))  # EAST, WEST: each faces the other
    _, s2, _, done, info = jax.jit(macro.step)(None, head_on, options, p)
    assert int(info["steps"]) == (patience or 7) and s2.agent_pos.tolist() == s.agent_pos.tolist()
    # both bound east, medic 1 ahead: medic 0 (acting first) finds the cell taken, yet it moves next step
    follow = s.replace(agent_dir=jnp.array([0, 0]))
    east = jnp.array([options[0], options[0]])
    _, s3, _, _, info = jax.jit(macro.step)(None, follow, east, p)
    assert int(info["steps"]) == 4  # medic 1 reaches b_room (1, 9) in 4 steps; medic 0 lost one, first
    assert s3.agent_pos.tolist() == [[1, 7], [1, 9]]


def test_own_termination_lets_the_other_options_run_on():
    """termination=own: medic 0 (bound west) reaches a_room in 3 steps; medic 1's NAVIGATE-TO-B runs on, is
    in the abstract state and is its only valid choice, and keeps counting its steps; with the paper's rule
    both options end."""
    for own in (False, True):
        macro, options, p = _corridor_macro(own_termination=own)
        _, s = macro.reset(None)
        s = s.replace(env=s.env.replace(agent_dir=jnp.array([2, 0])))  # medic 0 WEST, medic 1 EAST
        to_a, to_b = int(options[1]), int(options[0])
        obs, s2, _, _, info = jax.jit(macro.step)(None, s, jnp.array([to_a, to_b]), p)
        assert int(info["steps"]) == 3 and s2.agent_pos.tolist() == [[1, 1], [1, 8]]
        assert s2.running.tolist() == ([-1, to_b] if own else [-1, -1])
        assert s2.elapsed.tolist() == ([0, 3] if own else [0, 0])
        valid = np.asarray(macro.valid_options(obs))
        assert valid[1].tolist() == ([o == to_b for o in range(macro.options.n)] if own else
                                     np.asarray(macro.available(*macro.decode(obs)))[1].tolist())
        assert macro.running_of(obs).tolist() == s2.running.tolist()
        if own:  # medic 0 takes its room's triage; medic 1 arrives one step later, its option 4 steps old
            triage = macro.options.names.index("TRIAGE-A-VICTIM")
            _, s3, _, _, info = jax.jit(macro.step)(None, s2, jnp.array([triage, to_b]), p)
            assert int(info["steps"]) == 1 and s3.running.tolist() == [triage, -1]
            assert s3.elapsed.tolist() == [1, 0]


def test_cell_features_say_where_medics_stand_and_keep_the_abstract_state():
    plain, _, _ = _corridor_macro()
    macro, _, _ = _corridor_macro(cells=True)
    _, s = macro.reset(None)
    obs = macro.observe(s)
    env = macro.env
    assert obs.shape == (plain.obs_dim + 2 * (env.height + env.width),) == (macro.obs_dim,)
    assert sum(macro.obs_blocks) == macro.obs_dim
    tail = np.asarray(obs[plain.obs_dim:]).reshape(2, env.height + env.width)
    assert [np.flatnonzero(t).tolist() for t in tail] == [[1, env.height + 4], [1, env.height + 5]]
    np.testing.assert_array_equal(obs[: plain.obs_dim], plain.observe(s))
    for a, b in zip(macro.decode(obs), plain.decode(plain.observe(s))):
        np.testing.assert_array_equal(a, b)


def test_smdp_row_marks_invalid_choices_terminal(two_rooms):
    env, opts = two_rooms
    macro = _macro(env, opts)
    learner = coord.make_learner(macro, config.CoordinatorConfig())
    row = learner.row_fn({"obs": jnp.zeros(8), "action": jnp.array([0]), "reward": jnp.float32(-100),
                          "next_obs": jnp.zeros(8), "done": jnp.bool_(False),
                          "info": {"terminated": jnp.bool_(False), "valid": jnp.bool_(False), "steps": jnp.int32(1),
                                   "discounted_reward": jnp.float32(-100)}})
    assert bool(row["terminal"]) and float(row["reward"]) == -100.0
    np.testing.assert_allclose(float(row["gamma"]), 0.95)
    # a valid option of k = 3 steps discounts its bootstrap by gamma^3 (the SMDP target)
    row = learner.row_fn({"obs": jnp.zeros(8), "action": jnp.array([0]), "reward": jnp.float32(0),
                          "next_obs": jnp.zeros(8), "done": jnp.bool_(False),
                          "info": {"terminated": jnp.bool_(False), "valid": jnp.bool_(True), "steps": jnp.int32(3),
                                   "discounted_reward": jnp.float32(0)}})
    assert not bool(row["terminal"])
    np.testing.assert_allclose(float(row["gamma"]), 0.95 ** 3, rtol=1e-6)


def _oracle_macro(env, navigation, cfg):
    opts = options_from_graph(env.graph, navigation, env)
    tasks = sp.make_tasks(env, opts, navigation=navigation)
    params = sp.task_params(env, tasks, 0.99, {})
    senv = sp.SubtaskEnv(env, env.horizon, n_goals=max(len(t.goals) for t in tasks))
    sub = sp.exact_subpolicies(senv, params)
    macro = coord.MacroEnv(env, opts, sp.policy_table(env, opts, tasks, navigation), sp.table_act(senv),
                           senv.observe, cfg.gamma, cfg.invalid_penalty,
                           cfg.option_timeout or auto_option_timeout(env, opts, tasks, params),
                           factored=cfg.kind == "factored", block_patience=cfg.block_patience, dodge=cfg.dodge,
                           cells=cfg.features == "cells", own_termination=cfg.termination == "own",
                           option_goals=sp.option_goals(opts, tasks))
    return macro, tasks, sub


def _oracle_coordinator(episodes=60, trials=2, seed=0, map="two_rooms", navigation="adjacent", optimal=18,
                        **overrides):
    """The coordinator trained over exact ("oracle") sub-policies."""
    env = envs.make(map, horizon=300)
    cfg = config.CoordinatorConfig(episodes=episodes, **overrides)
    macro, tasks, sub = _oracle_macro(env, navigation, cfg)
    if map == "two_rooms":
        assert [t.name for t in tasks[:4]] == ["agent0:NAVIGATE-TO-TOP-ROOM", "agent1:NAVIGATE-TO-TOP-ROOM",
                                               "agent0:NAVIGATE-TO-BOTTOM-ROOM", "agent1:NAVIGATE-TO-BOTTOM-ROOM"]
    learner = coord.make_learner(macro, cfg)
    from jaxusar.core import Trainer

    tc = config.TrainConfig(episodes=episodes, test_every=1, chunk_steps=64)
    trainer = Trainer(macro, learner, tc, learning_starts=cfg.learning_starts, train_every=1, optimal_steps=optimal,
                      min_episode_steps=1, gradient_steps=cfg.gradient_steps)
    keys = jax.random.split(jax.random.PRNGKey(seed), trials)
    sub_b = jax.tree.map(lambda x: jnp.broadcast_to(x, (trials, *x.shape)), sub)
    state = trainer.train(keys, env_params=coord.CoordinatorParams(subpolicy=sub_b))
    return env, macro, learner, trainer.results(state), sub


def test_coordinator_learns_the_papers_assignment_with_exact_subpolicies():
    """Over exact sub-policies the coordinator alone is tested: most trials find the 18-step plan."""
    env, macro, learner, res, sub = _oracle_coordinator(episodes=100, trials=8)
    optimal = [k for k, e in enumerate(res["episodes_to_optimal"]) if e is not None]
    assert len(optimal) >= 6, res["episodes_to_optimal"]  # measured: 7 of 8, median 22.5 episodes
    for k in optimal:
        params = jax.tree.map(lambda x: x[k], res["best_params"])
        obs, _ = macro.reset(None)
        first = int(learner.greedy_act(params, obs, None)[0][0])
        # Sec. IV-B: the top medic goes to the bottom room, the bottom medic to the top room
        assert [macro.options.names[o] for o in macro.joint[first]] == ["NAVIGATE-TO-BOTTOM-ROOM",
                                                                        "NAVIGATE-TO-TOP-ROOM"]
        assert res["best_return"][k] == 200.0 and res["best_length"][k] == 18


def _policy_tables(senv, params, k, noise: float, seed: int):
    """An action table int[G, H, W, 4] for task k (per goal index): a shortest-path action everywhere,
    replaced by a random action in a ``noise`` fraction of the states; and the numpy successor tables to
    roll it out."""
    nxt, hit = (np.asarray(x) for x in planning._single_agent_successors(jnp.asarray(params.solid[k]),
                                                                            jnp.asarray(params.victim_at[k][0])))
    table = np.asarray(sp.exact_subpolicies(senv, params)[k])
    rng = np.random.default_rng(seed)
    flip = rng.random(table.shape) < noise
    return np.where(flip, rng.integers(0, 4, table.shape), table), nxt, hit


@pytest.mark.parametrize("navigation,k,noise", [("adjacent", 0, 0.0), ("adjacent", 2, 0.05), ("adjacent", 3, 0.2),
                                                ("adjacent", 4, 0.1), ("adjacent", 5, 0.3), ("goal", 0, 0.0),
                                                ("goal", 0, 0.05)])
def test_coverage_equals_a_rollout_from_every_initiation_state(navigation, k, noise):
    """SubtaskEnv.coverage (one batched fixed point) against a plain rollout from each initiation state
    (with goal navigation: each state and goal room): a state counts when the rollout reaches the sub-goal
    in exactly the planner's distance; and which states count, state by state."""
    env = envs.make("two_rooms", horizon=300)
    opts = options_from_graph(env.graph, navigation)
    tasks = sp.make_tasks(env, opts, navigation=navigation)
    params = sp.task_params(env, tasks, 0.99, {})
    senv = sp.SubtaskEnv(env, env.horizon, n_goals=len(tasks[k].goals))
    table, nxt, hit = _policy_tables(senv, params, k, noise, seed=k)
    h, w = env.height, env.width

    def greedy(obs):
        r, c, d = jnp.argmax(obs[:h]), jnp.argmax(obs[h:h + w]), jnp.argmax(obs[h + w:h + w + 4])
        g = jnp.argmax(obs[-senv.n_goals:]) if senv.n_goals else 0
        return jnp.asarray(table)[g, r, c, d].reshape(1)

    good = []
    for r, c, d, g in tasks[k].initiation:
        goal = int(params.goal_region[k][g])
        s, steps, done = (r, c, d), 0, False
        while not done and steps <= 60:
            a = table[g][s]
            done = bool(hit[s][a]) or (goal >= 0 and env.graph.cell_region[tuple(nxt[s][a][:2])] == goal)
            s, steps = tuple(nxt[s][a]), steps + 1
        good.append(done and steps == params.dist[k][g, r, c, d])
    p = jax.tree.map(lambda x: jnp.asarray(x[k]), params)
    got, states = jax.jit(senv.coverage, static_argnums=0)(greedy, p)
    assert float(got) == pytest.approx(np.mean(good), abs=1e-6)
    n = len(good)
    assert list(np.asarray(states[:n])) == good and not np.asarray(states[n:]).any()  # padding never counts
    got = float(got)
    assert (got == 1.0) == (noise == 0.0)  # exact everywhere, and the noisy tables miss some states


def test_focus_starts_draw_from_the_states_the_last_test_failed(two_rooms):
    """``focus``: that fraction of starts is drawn uniformly from ``weak`` (the initiation states the last test
    was not optimal from), the rest as the task says; no weak state, or focus 0, draws as the task says."""
    env, opts = two_rooms
    tasks = sp.make_tasks(env, opts, navigate_start="mixed")
    params = sp.task_params(env, tasks, 0.99, {})
    k = 0  # agent0's navigation: half its starts are the medic's start
    p = jax.tree.map(lambda x: jnp.asarray(x[k]), params)
    init = np.asarray(p.initiation)
    good = np.ones(len(init), bool)
    good[[5, 17]] = False
    keys = jax.random.split(jax.random.PRNGKey(0), 4000)
    starts = lambda senv, p: np.asarray(jax.vmap(senv.reset, in_axes=(0, None))(keys, p)[1].agent_pos[:, 0])

    full, half, none = (sp.SubtaskEnv(env, 50, focus=f) for f in (1.0, 0.5, 0.0))
    weak = full.refocus(p, jnp.asarray(good))
    assert np.flatnonzero(np.asarray(weak.weak)).tolist() == [5, 17]
    got = starts(full, weak)
    assert {tuple(x) for x in got} == {tuple(init[5, :2]), tuple(init[17, :2])}
    from_weak = np.mean([tuple(x) in {tuple(init[5, :2]), tuple(init[17, :2])} for x in starts(half, weak)])
    assert 0.5 < from_weak < 0.56  # half drawn there, plus the uniform half's few hits
    assert not np.asarray(full.refocus(p, jnp.ones(len(init), bool)).weak).any()
    mixed = starts(full, p)  # nothing weak: the task's own starts, half of them the medic's
    assert 0.45 < np.mean((mixed == env.layout.agent_start[0]).all(1)) < 0.55
    # focus 0 draws exactly as before focus existed
    old = np.asarray(jax.vmap(lambda key: p.starts[jax.random.randint(key, (), 0, p.n_starts)])(keys))[:, :2]
    np.testing.assert_array_equal(starts(none, weak), old)
    # padding never becomes weak: triage tasks pad their initiation states to the navigation tasks' count
    kt = [t.name for t in tasks].index("TRIAGE-BOTTOM-VICTIM")
    pt = jax.tree.map(lambda x: jnp.asarray(x[kt]), params)
    assert int(full.refocus(pt, jnp.zeros(pt.initiation.shape[0], bool)).weak.sum()) == len(tasks[kt].initiation)


def test_trainer_refocuses_on_the_latest_test():
    """After training, a lane's weak states are exactly what its latest test's coverage missed."""
    cfg = config.load(None, ["train.episodes=40", "train.stop_at_optimal=false", "train.chunk_steps=500",
                             "dqn.learning_starts=100", "hierarchical.focus_starts=0.5"],
                      defaults=algos_defaults("hierarchical"))
    exp = hierarchical.Experiment(cfg, jax.random.split(jax.random.PRNGKey(3), 1))
    stage = exp.chains[0][0]
    assert stage.trainer.env.focus == 0.5
    state = stage.trainer.train(stage.keys, env_params=stage.env_params)
    t = jax.device_get(state.trials)
    last = t.test_coverage[:, -2]  # the last test (the final slot is a write-off)
    n_weak = t.env_params.weak.sum(-1)
    assert np.array_equal(n_weak, np.round((1 - last) * t.env_params.n_initiation).astype(int))
    assert (n_weak > 0).any()  # 40 episodes: some task still misses states


# -- chained navigation, the factored coordinator, maps beyond two rooms ----------------------------------
def test_next_hop_follows_the_region_graph():

    # regions 0 - 1 - 2 - 3 in a line, 4 alone
    adj = np.zeros((5, 5), bool)
    for a, b in ((0, 1), (1, 2), (2, 3)):
        adj[a, b] = adj[b, a] = True
    hop = next_hop(adj)
    assert hop[0, 3] == 1 and hop[1, 3] == 2 and hop[2, 3] == 3 and hop[3, 0] == 2
    assert hop[0, 0] == -1 and hop[0, 4] == -1 and hop[4, 0] == -1  # itself, unreachable


def test_chained_navigation_reaches_any_room_with_one_subpolicy_per_region():
    """office: 9 rooms off a corridor cut into pieces, 4 medics. Chained: one navigation task per region on some
    shortest region path to a room (every region but the corridor's dead-end piece), shared by the medics (never
    medics x rooms^2); NAVIGATE-TO-R starts anywhere but R and runs, piece by piece, to R's door, then into R."""
    env = envs.make("office", horizon=300)
    g = env.graph
    opts = options_from_graph(g, "chained")
    tasks = sp.make_tasks(env, opts, navigation="chained")
    nav = [t for t in tasks if t.victim < 0]
    hops = {int(h) for h in next_hop(g.adjacency)[:, list(g.rooms)].ravel() if h >= 0}
    assert sorted(t.region for t in nav) == sorted(hops) and len(nav) == g.n_regions - 1
    assert all(t.agent == -1 for t in nav) and len(tasks) == len(nav) + env.n_victims
    table = sp.policy_table(env, opts, tasks, "chained")
    room0, room5 = g.index("room_0"), g.index("room_5")
    door = lambda room: int(np.flatnonzero(g.adjacency[room])[0])  # the corridor piece a room opens on
    to5 = opts.names.index("NAVIGATE-TO-ROOM-5")
    assert tasks[table[0, room0, to5]].region == door(room0) and g.kinds[door(room0)] == "hall"
    assert tasks[table[3, door(room5), to5]].name == "NAVIGATE-TO-ROOM-5"
    assert table[0, room5, to5] == -1  # not from inside the room itself
    assert bool(opts.can_initiate(room0, jnp.zeros(env.n_victims, bool))[to5])


def test_goal_navigation_is_one_subpolicy_for_every_room_and_medic():
    """office, goal navigation: a single navigation task, its goals every room, started anywhere outside
    the goal room (any facing); every medic's NAVIGATE-TO-R runs it, told R, from every region but R."""
    env = envs.make("office", horizon=300)
    opts = options_from_graph(env.graph, "goal")
    tasks = sp.make_tasks(env, opts, navigation="goal")
    nav = [t for t in tasks if t.victim < 0]
    assert len(nav) == 1 and len(tasks) == 1 + env.n_victims
    task, g = nav[0], env.graph
    assert task.goals == g.rooms == tuple(opts.region[opts.kind == NAVIGATE]) and task.option == -1
    victims = {tuple(v) for v in env.layout.victim_pos}
    for i, room in enumerate(task.goals):
        rows = task.initiation[task.initiation[:, 3] == i]
        open_cells = [(r, c) for r, c in np.argwhere((g.cell_region >= 0) & (g.cell_region != room))
                      if (r, c) not in victims]
        assert sorted(map(tuple, rows[:, :3].tolist())) == sorted((r, c, d) for r, c in open_cells for d in range(4))
    table, goals = sp.policy_table(env, opts, tasks, "goal"), sp.option_goals(opts, tasks)
    hall, room5 = g.index("hall_0"), g.index("room_5")
    to5 = opts.names.index("NAVIGATE-TO-ROOM-5")
    assert task.goals[goals[to5]] == room5
    assert (table[:, :, to5] == 0).all() and (table == table[:, :1]).all()  # the same task in every region
    assert bool(opts.can_initiate(hall, jnp.zeros(env.n_victims, bool))[to5])
    assert not bool(opts.can_initiate(room5, jnp.zeros(env.n_victims, bool))[to5])  # not from inside the room
    triage = np.flatnonzero(opts.kind == TRIAGE)
    assert (goals[triage] == 0).all() and (table[:, :, triage] >= 1).all()
    params = sp.task_params(env, tasks, 0.99, {})
    assert params.dist.shape[:2] == (len(tasks), len(task.goals)) and params.starts.shape[-1] == 4
    one_room = envs.make(envs.parse_layout("A..V\n....", "R r_room room\n---\nRRRR\nRRRR", "one"))
    opts = options_from_graph(one_room.graph, "goal")  # nowhere to navigate from: triage only
    assert [t.name for t in sp.make_tasks(one_room, opts, navigation="goal")] == ["TRIAGE-R-VICTIM"]


def test_adjacent_navigation_names_a_room_out_of_reach():
    """Rooms in a row, A - B - C: the paper's adjacent sub-policies take the medic in A to B only, so C's victim
    is out of reach (a one-line error naming the room and the fix); chained navigation reaches it by B."""
    from jaxusar.experiments.hierarchical import check_rooms_reachable

    grid = "A..#...#..V\n...........\n...#...#..."
    regions = "A a_room room\nB b_room room\nC c_room room\n---\nAAA#BBB#CCC\nAAABBBBCCCC\nAAA#BBB#CCC"
    env = envs.make(envs.parse_layout(grid, regions, "row"))
    for navigation in ("adjacent", "chained"):
        opts = options_from_graph(env.graph, navigation)
        table = sp.policy_table(env, opts, sp.make_tasks(env, opts, navigation=navigation), navigation)
        if navigation == "adjacent":
            with pytest.raises(ConfigError, match="'c_room'.*navigation=chained"):
                check_rooms_reachable(env, opts, table, navigation)
        else:
            check_rooms_reachable(env, opts, table, navigation)
            to_c = opts.names.index("NAVIGATE-TO-C-ROOM")
            assert table[0, env.graph.index("a_room"), to_c] >= 0


def coord_defaults():
    return {"algo": "hierarchical", **coord.DEFAULTS}


@pytest.mark.parametrize("navigation", ["chained", "goal"])
def test_a_navigate_option_runs_across_regions_to_its_room(navigation):
    """Over exact sub-policies, one macro step of NAVIGATE-TO-ROOM-5 from inside room_0 ends in room_5, by the
    hall, within a few steps of the single-medic shortest path (chained), or on it (goal-conditioned)."""
    env = envs.make(envs.load_layout("office").subset(agents=[0]), horizon=300)  # one medic: no other option ends it
    cfg = config.CoordinatorConfig(kind="factored")
    macro, tasks, sub = _oracle_macro(env, navigation, cfg)
    g = env.graph
    room0, room5 = g.index("room_0"), g.index("room_5")
    _, s = env.reset(None)
    cell = np.argwhere(g.cell_region == room0)[0]
    s = s.replace(agent_pos=s.agent_pos.at[0].set(jnp.asarray(cell)))
    options = np.array([macro.options.names.index("NAVIGATE-TO-ROOM-5")], np.int32)
    obs, s2, _, _, info = jax.jit(macro.step)(None, s, jnp.asarray(options), coord.CoordinatorParams(subpolicy=sub))
    assert bool(info["valid"])
    assert int(g.cell_region[tuple(np.asarray(s2.agent_pos[0]))]) == room5
    shortest = planning.steps_to_goal(env.layout.blocked, np.full(env.layout.shape, -1, np.int32),
                                      g.cell_region == room5)[tuple(cell) + (int(s.agent_dir[0]),)]
    assert shortest <= int(info["steps"]) <= shortest + (2 if navigation == "chained" else 0)


def test_factored_coordinator_sums_per_medic_heads():
    """FactoredDQN: Q(s, a) = sum_i Q_i(s, a_i); the target maximises each head over its valid options;
    greedy choices respect each medic's mask; parameters grow linearly in the medics."""
    from jaxusar.core.learners import FactoredDQN

    cfg = config.DQNConfig(hidden=(8,), batch_size=2, buffer_capacity=4)
    valid = lambda obs: jnp.array([[True, False, True], [False, True, True]])
    f = FactoredDQN(3, 3, 2, cfg, valid)
    q = jnp.array([[1.0, 2.0, 3.0, 10.0, 20.0, 30.0], [0.0, 5.0, -1.0, 7.0, 8.0, -9.0]])
    np.testing.assert_allclose(f._joint_value(q, jnp.array([[0, 2], [1, 0]])), [1.0 + 30.0, 5.0 + 7.0])
    batch = {"reward": jnp.array([1.0, 2.0]), "discount": jnp.array([0.5, 0.0]), "next_obs": jnp.zeros((2, 3))}
    # head 0 over options {0, 2}, head 1 over {1, 2}: row 0: 3 + 30; row 1: terminal
    np.testing.assert_allclose(f._target(batch, q, q), [1.0 + 0.5 * 33.0, 2.0])
    state = f.init(jax.random.PRNGKey(0), {"obs": jnp.zeros(3), "action": jnp.zeros(2, jnp.int32),
                                           "reward": jnp.float32(0), "next_obs": jnp.zeros(3),
                                           "info": {"terminated": jnp.bool_(False)}, "done": jnp.bool_(False)})
    a, _ = f.greedy_act(state.params, jnp.ones(3), None)
    assert a.shape == (2,) and int(a[0]) in (0, 2) and int(a[1]) in (1, 2)
    size = lambda n: sum(x.size for x in jax.tree.leaves(
        FactoredDQN(3, 15, n, cfg, None).dqn.network.init(jax.random.PRNGKey(0), jnp.zeros(3))))
    assert size(4) - size(2) == 2 * (size(3) - size(2))  # linear in the medics (the flat head: 15^n)


def test_flat_coordinator_refuses_too_many_joint_options():
    from jaxusar.experiments.hierarchical import build

    with pytest.raises(ConfigError, match=r"50,625 joint options \(15 options \^ 4 agents\).*factored"):
        build(config.load(None, ["env.map=office", "hierarchical.coordinator.kind=flat"], defaults=coord_defaults()))


def test_the_coordinator_stops_at_optimal_by_config():
    """hierarchical.coordinator.stop_at_optimal reaches the coordinator's trainer (on by default), not the
    sub-policies' (train.stop_at_optimal); what stopping keeps is tested on the trainer (test_core). The
    coordinator keeps stopped trials in its batch (its chunks cost less than a smaller batch's compile)."""
    for sets, want in [([], True), (["hierarchical.coordinator.stop_at_optimal=false"], False)]:
        b = hierarchical.build(config.load(None, sets + ["train.stop_at_optimal=false"], defaults=coord_defaults()))
        assert b["coord_trainer"].cfg.stop_at_optimal is want and b["sub_trainer"].cfg.stop_at_optimal is False
        assert not b["coord_trainer"].drop_finished and b["sub_trainer"].drop_finished


@pytest.mark.parametrize("termination", ["all", "own"])
def test_the_team_episode_picture_replays_the_greedy_test(termination):
    """``team_episode`` (the pictures' step-by-step replay) takes exactly the steps and reward of the
    trainer's best greedy test, under either termination rule."""
    from jaxusar.experiments.hierarchical import team_episode

    env, macro, learner, res, sub = _oracle_coordinator(episodes=30, trials=1, kind="factored",
                                                        termination=termination, block_patience=2)
    states, rewards, _ = team_episode(macro, learner, jax.tree.map(lambda x: x[0], res["best_params"]), sub)
    assert len(rewards) == int(res["best_length"][0]) and len(states) == len(rewards) + 1
    assert float(rewards.sum()) == pytest.approx(float(res["best_return"][0]))


def test_automatic_option_timeout():
    """0 = 1.5x the longest optimal option path, at least 50: 50 on two_rooms (its results unchanged),
    more on office, where crossing the map to a room takes 55 steps."""
    from jaxusar.experiments.hierarchical import build

    two = build(config.load(None, [], defaults=coord_defaults()))
    assert two["macro"].option_timeout == 50
    office = build(config.load(None, ["env.map=office"], defaults=coord_defaults()))
    assert office["macro"].option_timeout == 83  # ceil(1.5 * 55)
    # office's settings file: options that run to their own end (two_rooms keeps the paper's rule)
    assert office["macro"].own_termination and not two["macro"].own_termination


def test_factored_coordinator_solves_four_rooms_over_exact_subpolicies():
    """The factored coordinator over exact chained sub-policies, three medics: every trial triages all four
    victims, and the best team is within 1.25x of the lower bound (25 steps)."""
    bound = planning.team_lower_bound(envs.make("four_rooms"))
    env, macro, learner, res, _ = _oracle_coordinator(episodes=60, trials=2, map="four_rooms", navigation="chained",
                                                      optimal=bound, kind="factored")
    assert all(e is not None for e in res["episodes_to_solved"]), res["episodes_to_solved"]
    assert all(length <= 1.25 * bound for length in res["best_length"]), res["best_length"]


# -- rubble and engineers (contract part 2) ----------------------------------------------------------
@pytest.fixture(scope="module")
def rubble_options():
    env = envs.make("two_rooms_rubble", horizon=300)
    return env, options_from_graph(env.graph, "chained", env)


def test_rubble_groups_are_touching_cells():
    two = Rubble.of(envs.make("two_rooms_rubble").layout)
    assert two.cells.tolist() == [[6, 12], [7, 12]] and two.group.tolist() == [0, 0] and two.n_configs == 2
    mini = Rubble.of(envs.make("minimap").layout)
    assert mini.n_groups == 3 and mini.group_bits.tolist() == [1, 2, 4]
    rubble = jnp.asarray(two.index >= 0).at[6, 12].set(False)  # one cell of the group cleared
    assert int(two.mode_of(rubble)) == 1 and int(two.config_of(two.mode_of(rubble))) == 0
    assert int(two.config_of(two.mode_of(jnp.zeros_like(rubble)))) == 1


def test_clear_options_are_the_engineers_and_navigation_waits_at_the_rubble(rubble_options):
    env, opts = rubble_options
    assert opts.names[-1] == "CLEAR-RUBBLE-0" and opts.kind[-1] == CLEAR
    hall, bottom, none = env.graph.index("hall_way"), env.graph.index("bottom_room"), jnp.zeros(2, bool)
    to_bottom, triage_bottom = opts.names.index("NAVIGATE-TO-BOTTOM-ROOM"), opts.names.index("TRIAGE-BOTTOM-VICTIM")
    medic, engineer = 0, 1
    blocked = np.asarray(opts.can_initiate(hall, none, 0, medic))
    assert blocked[to_bottom] and not blocked[-1]  # towards the rubble in the way, to wait; medics never clear
    assert np.asarray(opts.can_initiate(hall, none, 1, medic))[to_bottom]
    assert np.asarray(opts.can_initiate(hall, none, 0, engineer))[-1]
    assert not np.asarray(opts.can_initiate(bottom, none, 1, engineer))[triage_bottom]  # engineers never triage
    assert not np.asarray(opts.can_initiate(hall, none, 1, engineer))[-1]  # nothing left to clear
    assert bool(opts.terminated(len(opts.names) - 1, hall, none, 1)) and not bool(opts.terminated(4, hall, none, 0))


def test_the_method_counts_rubble_in_a_doorway_as_the_hall():
    """NAVIGATE-TO-BOTTOM-ROOM ends past the doorway's rubble, so an engineer that cleared it and walked in
    stands aside (the optimum's engineer does); the env's own regions (what "view" shows) stay."""
    from jaxusar.experiments.hierarchical import build

    env = envs.make("two_rooms_rubble")
    view = method_env(env)
    hall, bottom = env.graph.index("hall_way"), env.graph.index("bottom_room")
    assert np.argwhere(view.graph.cell_region != env.graph.cell_region).tolist() == [[6, 12], [7, 12]]
    assert (view.graph.cell_region[6:8, 12] == hall).all() and (env.graph.cell_region[6:8, 12] == bottom).all()
    two = envs.make("two_rooms")
    assert method_env(two) is two  # no rubble: the same env, the same programs
    # rubble inside a room (touching no other region) stays the room's; so does rubble whose loss would
    # split the room in two
    inner = envs.parse_layout("A....\n.....\n..r..\nE...V", "T top hall\nR r_room room\n---\nTTTTT\n"
                              "RRRRR\nRRRRR\nRRRRR", "inner")
    split = envs.parse_layout("A....\n..r..\nE.#.V", "T top hall\nR r_room room\n---\nTTTTT\nRRRRR\nRR#RR",
                              "split")
    for layout in (inner, split):
        assert np.array_equal(doorway_rubble_regions(layout), layout.region), layout.name
    b = build(config.load(None, ["env.map=two_rooms_rubble"], defaults=coord_defaults()))
    k = [t.name for t in b["tasks"]].index("NAVIGATE-TO-BOTTOM-ROOM")
    east = 0
    assert b["task_params"].dist[k][3, 7, 10, east] == 3  # cleared: three steps, past the doorway's cells


def test_steps_to_clear_counts_the_engineers_tool():
    env = envs.make("two_rooms_rubble")
    two = Rubble.of(env.layout)
    dist = planning.steps_to_clear(env.layout.blocked, two.cells, int(two.group_bits[0]))
    east, north = 0, 3
    assert dist[0, 7, 11, east] == 4  # clear (7,12), step into it, turn north, clear (6,12)
    assert dist[0, 7, 10, east] == 5 and dist[2, 6, 11, east] == 1  # (7,12) already cleared: one TRIAGE
    assert dist[0, 7, 12, north] == -1 and dist[3, 7, 11, east] == 0  # inside rubble; nothing left to clear
    assert dist[2, 7, 12, north] == 1  # (7,12) cleared, standing in it facing (6,12)


def test_rubble_subtasks_are_exact_in_every_mode(rubble_options):
    """The planner's tables (numpy, ``steps_to_clear``/``steps_to_goal`` per mode) and the sub-task's own
    rules (jax, ``SubtaskEnv._transition``) agree: the greedy policy of the tables is optimal from every
    initiation state of every task, in every mode."""
    env, opts = rubble_options
    tasks = sp.make_tasks(env, opts, navigation="chained")
    assert [t.name for t in tasks][-1] == "CLEAR-RUBBLE-0"
    params = sp.task_params(env, tasks, 0.95, {})
    senv = sp.SubtaskEnv(env, env.horizon, "cell")
    assert senv.obs_dim == 10 + 15 + 4 + 1 + 150 + 2  # a cleared flag per rubble cell
    act, tables = sp.table_act(senv), sp.exact_subpolicies(senv, params)
    for k, t in enumerate(tasks):
        p = jax.tree.map(lambda x: jnp.asarray(x[k]), params)
        assert float(senv.coverage(lambda obs: act(tables[k], obs), p)[0]) == 1.0, t.name
        assert set(t.initiation[:, 3] % senv.n_modes) <= set(range(4))
    clear = tasks[-1]
    assert not (clear.initiation[:, 3] == 3).any()  # no CLEAR state where the group is cleared
    never = jax.tree.map(lambda x: jnp.asarray(x[len(tasks) - 1]), params)
    assert float(senv.coverage(lambda obs: jnp.array([0]), never)[0]) == 0.0  # always FORWARD never clears


def test_the_coordinator_clears_then_triages_with_exact_subpolicies():
    env = envs.make("two_rooms_rubble", horizon=300)
    cfg = config.CoordinatorConfig(kind="factored", dodge=True)
    macro, tasks, sub = _oracle_macro(env, "chained", cfg)
    p = coord.CoordinatorParams(subpolicy=sub)
    names = macro.options.names
    obs, s = macro.reset(None)
    assert obs.shape == (macro.obs_dim,) and macro.obs_blocks[-1:] == (1,) and float(obs[-1]) == 0.0
    valid = np.asarray(macro.valid_options(obs))
    assert valid[2, names.index("CLEAR-RUBBLE-0")] and not valid[0, names.index("CLEAR-RUBBLE-0")]
    assert valid[1, names.index("NAVIGATE-TO-BOTTOM-ROOM")]
    plan = [("NAVIGATE-TO-TOP-ROOM", "NAVIGATE-TO-TOP-ROOM", "CLEAR-RUBBLE-0")]
    obs, s, r, done, info = macro.step(None, s, jnp.array([names.index(o) for o in plan[0]]), p)
    assert bool(info["valid"])
    for _ in range(20):  # then by a fixed preference among the valid options
        if bool(done):
            break
        regions, triaged, config_ = macro.decode(obs)
        assert int(config_) == int(not jnp.asarray(s.env.rubble).any())
        valid = np.asarray(macro.valid_options(obs))
        prefer = [[names.index(n) for n in ranked] for ranked in (
            ("TRIAGE-TOP-VICTIM", "NAVIGATE-TO-TOP-ROOM"), ("TRIAGE-BOTTOM-VICTIM", "NAVIGATE-TO-BOTTOM-ROOM"),
            ("CLEAR-RUBBLE-0", "NAVIGATE-TO-TOP-ROOM"))]  # the engineer out of the way once a way is open
        choice = [next((o for o in prefer[i] if valid[i, o]), int(np.argmax(valid[i]))) for i in range(3)]
        obs, s, r, done, info = macro.step(None, s, jnp.array(choice), p)
    assert bool(jnp.all(s.env.triaged)) and not bool(s.env.rubble.any())


def test_too_much_rubble_for_the_subpolicies_is_a_one_line_error_before_anything_compiles():
    text = "---\nA......\nrrrrrrr\nE.....V\n"
    regions = "T top room\nB bottom room\n---\nTTTTTTT\nBBBBBBB\nBBBBBBB\n"
    env = envs.USAREnv(envs.parse_layout(text, regions, "rubbly"))
    with pytest.raises(ConfigError, match="'rubbly' has 7 rubble cells: the hierarchical method's sub-policies "
                                          "handle at most 6") as err:
        options_from_graph(env.graph, "chained", env)
    assert "\n" not in str(err.value)


def test_navigation_cut_off_by_rubble_waits_next_to_it(rubble_options):
    """NAVIGATE-TO-BOTTOM-ROOM with the doorway's rubble in place: walk to a cell beside the rubble in the
    way and do a no-op there (its end in training); once cleared, the same task goes on into the room."""
    env, opts = rubble_options
    tasks = sp.make_tasks(env, opts, navigation="chained")
    k = [t.name for t in tasks].index("NAVIGATE-TO-BOTTOM-ROOM")
    params = sp.task_params(env, tasks, 0.95, {})
    wait = np.asarray(params.wait[k])
    assert np.argwhere(wait[0]).tolist() == [[6, 11], [7, 11]] and not wait[3].any()  # mode 3: all cleared
    east = 0
    assert params.dist[k][0, 7, 10, east] == 2 and params.dist[k][0, 7, 11, east] == 1  # then the no-op
    assert params.dist[k][3, 7, 10, east] == 2  # cleared: two steps into the room
    senv = sp.SubtaskEnv(env, env.horizon, "cell")
    p = jax.tree.map(lambda x: jnp.asarray(x[k]), params)
    *_, success, _ = senv._transition(jnp.array([7, 11]), jnp.int32(east), jnp.int32(3), jnp.int32(0), p)
    assert bool(success)
    *_, success, _ = senv._transition(jnp.array([7, 11]), jnp.int32(east), jnp.int32(3), jnp.int32(3), p)
    assert not bool(success)  # no waiting once the way is open


def _cells(rows: str, char: str) -> np.ndarray:
    return np.array([[c == char for c in row] for row in rows.split()])


@pytest.mark.parametrize("rows, waits", [
    # a one-wide rubbled doorway: its one clearing cell (2, 4) stays free for the engineer
    ("V..#...... ...#...... ...r...... ...#...... ...#......", [[1, 4], [2, 5], [3, 4]]),
    # rubble at the end of a one-wide corridor: waiting anywhere in it would shut the engineer out
    ("V..###### ...r..... ...####.. ...#.....", [[1, 8], [2, 7]]),
    # two_rooms_rubble's two-cell doorway: either clearing cell leaves the other to the engineer
    (None, [[6, 11], [7, 11]]),
])
def test_a_waiting_navigation_leaves_the_engineer_a_clearing_cell_and_a_way_to_it(rows, waits):
    if rows is None:
        env = envs.make("two_rooms_rubble")
        solid, rubble, goal = env._solid, np.asarray(env.layout.rubble), env.graph.cell_region == env.graph.names.index("bottom_room")
    else:
        solid, rubble = _cells(rows, "#"), _cells(rows, "r")
        goal = np.zeros_like(solid)
        goal[:, :3] = True  # the room behind the rubble
    assert np.argwhere(waiting_cells(solid, rubble, goal)).tolist() == waits


def _hall_macro(**kw):
    """Two medics face each other in the middle of an open hall."""
    macro, options, p = _forward_macro("V.........V\n...........\n....AA.....\n...........",
                                       "AACCCCCCCBB\n" * 4, 3, **kw)
    _, s = macro.reset(None)
    return macro, options, s.env.replace(agent_dir=jnp.array([0, 2])), p


@pytest.mark.parametrize("dodge", [False, True])
def test_dodge_lets_agents_meeting_head_on_in_the_open_step_aside(dodge):
    """Stopped by the other, each medic turns right and steps forward (south and north): 3 steps; without
    dodge both stand. A dodge does not end options, and a stop it follows still counts towards patience."""
    macro, options, s, p = _hall_macro(dodge=dodge)
    _, s2, _, _, info = jax.jit(macro.step)(None, s, options, p)
    assert int(info["steps"]) == 3
    assert s2.agent_pos.tolist() == ([[3, 4], [1, 5]] if dodge else [[2, 4], [2, 5]])
    assert s2.agent_dir.tolist() == ([1, 3] if dodge else [0, 2])
    blocked = macro.unblocked()
    for count, phase in ([1, 2], [1, 1], [0, 0]):  # stopped; turned (not moved); stepped aside (moved)
        s, _, _, blocked = macro.advance(s, options, jnp.array([True, True]), blocked, p)
        if dodge:
            assert blocked.tolist() == [[count] * 2, [phase] * 2]


@pytest.mark.parametrize("map_, kinds, message", [
    ("two_rooms", "[navigate,clear]", "without triage options no victim can be saved"),
    ("two_rooms", "[navigate,triage,clear]", "clear options need rubble and an engineer, and map 'two_rooms' has no rubble"),
    ("two_rooms", "[navigate,triage,search]", "search options need observation=view"),
    ("minimap", "[navigate,triage,search]", "builds no search options: under observation=view TRIAGE-IN-R searches"),
])
def test_an_option_kind_the_map_cannot_offer_is_a_one_line_error_before_anything_compiles(map_, kinds, message):
    cfg = config.load(None, [f"env.map={map_}", f"hierarchical.option_kinds={kinds}"],
                      defaults=algos_defaults("hierarchical"))
    with pytest.raises(ConfigError, match=re.escape(message)) as err:
        hierarchical.build(cfg)
    assert "\n" not in str(err.value) and str(err.value).startswith(f"hierarchical.option_kinds={kinds[1:-1]}: ")


@pytest.mark.parametrize("header, cell, message", [
    ("", "V", "victim 1 lies in 'hall', a hall: triage options need a room"),
    ("random_victims: 1 1\ncritical_triage_steps: 2\ncritical_expires: 40\n---\n", "?",
     "a victim may lie in 'hall', a hall: triage options need a room"),
])
def test_a_victim_outside_every_room_is_a_one_line_error_before_anything_compiles(tmp_path, header, cell, message):
    """A region grid that puts a victim (or a '?' cell) in a hall: the method's TRIAGE options are rooms'."""
    (tmp_path / "ward.txt").write_text(f"{header}{cell}..#...\nA..#..{cell}\n.......\n")
    (tmp_path / "ward.regions.txt").write_text("W west room\nE east room\nH hall hall\n---\nWWW#EEE\nWWW#HHH\nHHHHHHH\n")
    cfg = config.load(None, [f"env.map={tmp_path / 'ward.txt'}"], defaults=algos_defaults("hierarchical"))
    with pytest.raises(ConfigError, match=re.escape(message)) as err:
        hierarchical.build(cfg)
    assert "\n" not in str(err.value) and "region grid" in str(err.value)


def test_option_kinds_keep_only_the_named_kinds(rubble_options):
    env, every = rubble_options
    some = options_from_graph(env.graph, "chained", env, ("navigate", "triage"))
    assert some.names == tuple(n for n in every.names if not n.startswith("CLEAR"))
    keep = [every.names.index(n) for n in some.names]
    assert (some.open_from == every.open_from[..., keep]).all() and (some.kind != CLEAR).all()


DRAWN = "random_victims: 1 1\ncritical_triage_steps: 2\ncritical_expires: 40\n---\n?.?#?.?\n...#...\nA.....A\n"
DRAWN_REGIONS = "W west room\nE east room\nH hall hall\n---\nWWW#EEE\nWWW#EEE\nHHHHHHH\n"


def _drawn_macro(tmp_path, observation="full"):
    """The method on a small drawn-victim map (a regular and a critical victim drawn over four '?' cells,
    two rooms), over exact sub-policies: (macro env, subpolicy params)."""
    (tmp_path / "drawn.txt").write_text(DRAWN)
    (tmp_path / "drawn.regions.txt").write_text(DRAWN_REGIONS)
    cfg = config.load(None, [f"env.map={tmp_path / 'drawn.txt'}", f"env.observation={observation}"],
                      defaults=coord_defaults())
    b = hierarchical.build(cfg)
    return b["macro"], coord.CoordinatorParams(subpolicy=sp.exact_subpolicies(b["subtask_env"], b["task_params"]))


@pytest.mark.parametrize("map_name", ["two_rooms_rubble", "drawn"])
def test_the_coordinator_runs_trained_subpolicies_as_tables_of_their_greedy_actions(tmp_path, map_name):
    """``coordinator_params`` (``sp.greedy_tables``): over the tables, the macro env's decisions take
    the same primitive steps as over the networks themselves, on a map with rubble modes and one with
    goal-conditioned TRIAGE-IN-R (random networks, random valid options, two trials)."""
    import copy

    if map_name == "drawn":
        (tmp_path / "drawn.txt").write_text(DRAWN)
        (tmp_path / "drawn.regions.txt").write_text(DRAWN_REGIONS)
        map_name = str(tmp_path / "drawn.txt")
    cfg = config.load(None, [f"env.map={map_name}", "hierarchical.coordinator.kind=factored"],
                      defaults=coord_defaults())
    b = hierarchical.build(cfg)
    learner, n_tasks = b["sub_learner"], len(b["tasks"])
    init = lambda k: jax.tree.map(lambda x: x[None], learner.dqn.network.init(k, jnp.zeros(learner.dqn.input_shape)))
    nets = jax.vmap(init)(jax.random.split(jax.random.PRNGKey(3), 2 * n_tasks))
    nets = jax.tree.map(lambda x: x.reshape(2, n_tasks, *x.shape[1:]), nets)  # [trial, task, learner, ...]
    tables = b["coordinator_params"](nets)
    assert tables.subpolicy.shape == (2, n_tasks, *b["task_params"].dist.shape[1:])
    by_table = b["macro"]
    by_net = copy.copy(by_table)
    by_net.subpolicy_act = lambda p, obs: learner.greedy_act(p, obs, None)[0]
    steps = {m: jax.jit(lambda s, a, p, m=m: m.step(None, s, a, p)[1]) for m in (by_table, by_net)}
    senv, act = b["subtask_env"], sp.table_act(b["subtask_env"])
    rng = np.random.default_rng(0)
    for j in range(2):  # state by state: the table's action is the network's
        one = lambda tree: jax.tree.map(lambda x: x[j], tree)
        k, index = rng.integers(0, n_tasks, 300), rng.integers(0, tables.subpolicy.shape[2], 300)
        pos, d = np.stack([rng.integers(0, senv.height, 300), rng.integers(0, senv.width, 300)], -1), rng.integers(0, 4, 300)
        obs = jax.vmap(senv.observe, in_axes=(0, 0, None, 0))(jnp.asarray(pos), jnp.asarray(d), False, jnp.asarray(index))
        pick = lambda tree, k: jax.tree.map(lambda x: x[k], tree)
        want = jax.vmap(lambda k, o: learner.greedy_act(pick(one(nets), k), o, None)[0][0])(jnp.asarray(k), obs)
        got = jax.vmap(lambda k, o: act(pick(one(tables.subpolicy), k), o)[0])(jnp.asarray(k), obs)
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
        assert len(set(np.asarray(want).tolist())) >= 3
        _, s = by_table.reset(jax.random.PRNGKey(j))  # and decision by decision, the same steps
        s_net = s
        for _ in range(6):
            valid = np.asarray(by_table.valid_options(by_table.observe(s)))
            options = [rng.choice(np.flatnonzero(v)) for v in valid]
            s = steps[by_table](s, _joint(by_table, options), one(tables))
            s_net = steps[by_net](s_net, _joint(by_table, options), coord.CoordinatorParams(subpolicy=one(nets)))
            for a, c in zip(jax.tree.leaves(s), jax.tree.leaves(s_net)):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(c))


def _joint(macro, options) -> jax.Array:
    """The coordinator's action for per-agent ``options``: themselves (factored) or their joint index."""
    if macro.factored:
        return jnp.asarray(options, jnp.int32)
    return jnp.asarray([int(np.ravel_multi_index(tuple(options), (macro.options.n,) * macro.n_agents))], jnp.int32)


def test_drawn_victims_get_a_triage_option_per_room_that_works_slot_by_slot(tmp_path):
    """Full observation: TRIAGE-IN-R is offered to a medic in R while a slot of R holds a living untriaged
    victim, and a medic's NAVIGATE-TO-R likewise; over exact sub-policies it triages every victim of R, a
    critical one with two actions (the sub-policy's input does not change until then), one slot task at a
    time; the episode ends once every victim is triaged or dead."""
    macro, p = _drawn_macro(tmp_path)
    env, o = macro.env, macro.options
    assert env.observation == "full" and macro.n_slots == 4 and macro.n_flags == 2
    assert [o.names[k] for k in np.flatnonzero(o.kind == TRIAGE)] == ["TRIAGE-IN-WEST", "TRIAGE-IN-EAST"]
    assert [tuple(c) for c in macro.slots] == [(0, 0), (0, 2), (0, 4), (0, 6)] and o.slot_flag.tolist() == [0, 0, 1, 1]
    critical = int(np.flatnonzero(env.victim_kind == 1)[0])
    rooms = []
    for k in range(8):
        _, s = macro.reset(jax.random.PRNGKey(k))
        where = np.asarray(s.env.victim_pos)
        np.testing.assert_array_equal(np.asarray(macro.flags(s.env)), [not (where[:, 1] < 3).any(),
                                                                        not (where[:, 1] > 3).any()])
        room = "WEST" if where[critical, 1] < 3 else "EAST"
        rooms.append(room)
        medic, o_nav, o_tri = ("WEST", "EAST").index(room), o.names.index(f"NAVIGATE-TO-{room}"), \
            o.names.index(f"TRIAGE-IN-{room}")
        for option in (o_nav, o_tri):
            assert np.asarray(macro.valid_options(macro.observe(s)))[medic, option]
            for _ in range(10):  # decisions until the medic's option ends (the other's may end first)
                valid = np.asarray(macro.valid_options(macro.observe(s)))
                action = np.array([np.flatnonzero(v)[0] for v in valid], np.int32)
                action[medic] = option
                _, s, _, _, _ = macro.step(None, s, _joint(macro, action), p)
                if int(s.running[medic]) < 0:
                    break
        in_room = (where[:, 1] < 3) == (room == "WEST")
        assert np.asarray(s.env.triaged)[in_room].all() and int(s.env.progress[critical]) == 2
        assert bool(macro.flags(s.env)[("WEST", "EAST").index(room)])
        avail = np.asarray(macro.available(*macro.decode(macro.observe(s))))
        assert not avail[medic, o_tri] and not avail[1 - medic, o_nav]  # done: nothing left there
    assert set(rooms) == {"WEST", "EAST"}
    dead = s.env.replace(dead=jnp.ones_like(s.env.dead), triaged=jnp.zeros_like(s.env.triaged))
    assert np.asarray(macro.flags(dead)).all()  # a dead victim's room has nothing left to save
    _, _, _, done, info = macro.step(None, macro.wrap(dead), _joint(macro, [0, 0]), p)
    assert bool(done) and bool(info["terminated"])


def test_under_view_the_coordinator_knows_only_the_victims_the_team_has_seen(tmp_path):
    """The abstract state never holds an unseen victim's position: draws that differ only in unseen slots
    look the same to the coordinator; a room is done only once seen holding no victim to save, and its
    known victims are the ones seen."""
    macro, _ = _drawn_macro(tmp_path, "view")
    env = macro.env
    assert macro.view and env.view_radius is None  # the team sees a whole region at once
    _, s = macro.reset(jax.random.PRNGKey(0))
    assert not np.asarray(s.env.seen)[0].any()  # from the hall nobody sees into the rooms
    assert not np.asarray(macro.slot_done(s.env)).any()  # unseen: may hold a victim
    others = [macro.reset(jax.random.PRNGKey(k))[1] for k in range(1, 6)]
    assert len({tuple(np.asarray(o.env.victim_pos).ravel()) for o in [s, *others]}) > 1
    for other in others:  # other draws, the same abstract state
        np.testing.assert_array_equal(np.asarray(macro.observe(s)), np.asarray(macro.observe(other)))
    west = jnp.asarray(env.graph.cell_region == env.graph.index("west"))
    seen = s.env.replace(seen=s.env.seen | west)
    where = np.asarray(seen.victim_pos)
    in_west = int((where[:, 1] < 3).sum())
    assert bool(macro.flags(seen)[0]) == (in_west == 0) and not bool(macro.flags(seen)[1])
    known = np.asarray(macro.known(seen)[0])
    assert known.sum() == in_west and not known[2:].any()  # the west room's victims, none of the east's
    assert not np.array_equal(np.asarray(macro.observe(macro.wrap(seen))), np.asarray(macro.observe(s)))


def test_where_victims_are_drawn_every_test_plays_the_same_draws(tmp_path):
    """``train.test_draws`` (8 by default where victims are drawn): a test's return is the mean over the same
    draws at every test of a trial, so params that do not change score the same at every test (one draw
    per test scores each test on a new draw)."""
    (tmp_path / "drawn.txt").write_text(DRAWN)
    (tmp_path / "drawn.regions.txt").write_text(DRAWN_REGIONS)
    returns = {}
    for draws in (1, 8):
        sets = [f"env.map={tmp_path / 'drawn.txt'}", "hierarchical.coordinator.episodes=12",
                "hierarchical.coordinator.kind=factored",  # its greedy choice is among valid options
                "hierarchical.coordinator.learning_starts=100000", "hierarchical.coordinator.stop_at_optimal=false"]
        cfg = config.load(None, sets + ([f"train.test_draws={draws}"] if draws == 1 else []), defaults=coord_defaults())
        assert cfg.train.test_draws == draws  # 8: the map-derived default
        b = hierarchical.build(cfg)
        trainer = b["coord_trainer"]
        p = coord.CoordinatorParams(subpolicy=sp.exact_subpolicies(b["subtask_env"], b["task_params"])[None])
        returns[draws] = trainer.results(trainer.train(jax.random.PRNGKey(0)[None], env_params=p))["test_return"][0]
    assert len(set(returns[1].tolist())) > 1 and len(set(returns[8].tolist())) == 1


def test_a_room_triage_no_rubble_changes_is_learned_in_one_mode():
    """minimap (full observation): TRIAGE-IN-R, one task per room told the slot, has states in rubble mode 0
    only when no mode's rubble changes its shortest paths (the rooms' doorway rubble lies in the hall);
    navigation and clearing keep every mode."""
    cfg = config.load(None, ["env.map=minimap", "env.observation=full"], defaults=coord_defaults())
    b = hierarchical.build(cfg)
    modes = Rubble.of(b["env"].layout).n_modes
    triage = [t for t in b["tasks"] if t.targets]
    assert len(triage) == 6 and sum(len(t.targets) for t in triage) == len(b["env"].layout.random_cells)
    for t in b["tasks"]:
        assert t.every_mode == (not t.targets), t.name
        in_modes = set((t.initiation[:, 3] % modes).tolist())
        assert in_modes == {0} if t.targets else len(in_modes) > 1, t.name
    assert set(b["macro"].slot_every_mode.tolist()) == {False}
