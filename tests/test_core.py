"""The learning core: replay, target rules, epsilon, trainer (trials, determinism, tests, best params), IQL."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxusar import config, envs, planning
from jaxusar.algos import iql
from jaxusar.config import ConfigError, DQNConfig, TrainConfig
from jaxusar.core import IndependentDQN, Trainer, qlearning as ql, replay as rb
from jaxusar.envs import parse_layout

TINY = """
.V..
.A..
..AV
....
"""
TINY_REGIONS = "H hall hall\n---\nHHHH\nHHHH\nHHHH\nHHHH\n"


def tiny_env(**kw):
    return envs.make(parse_layout(TINY, TINY_REGIONS, "tiny"), **{"horizon": 20, **kw})


# -- replay -------------------------------------------------------------------------------------------
def test_replay_wraparound_and_size():
    buf = rb.init({"x": jnp.zeros((2,), jnp.int32)}, capacity=3)
    for i in range(5):
        buf = rb.add(buf, {"x": jnp.array([i, -i])})
    assert int(buf.size) == 3 and int(buf.pos) == 2
    # slots hold rows 3, 4, 2 (row 3 overwrote slot 0, row 4 slot 1)
    np.testing.assert_array_equal(buf.rows["x"][:, 0], [3, 4, 2])


def test_replay_samples_only_filled_slots_and_keeps_dtype():
    buf = rb.init({"x": jnp.zeros((), jnp.uint8)}, capacity=100)
    for i in range(1, 8):
        buf = rb.add(buf, {"x": jnp.uint8(i)})
    u = jax.random.uniform(jax.random.PRNGKey(0), (2000,))
    got = np.asarray(rb.sample(buf, u)["x"])
    assert got.dtype == np.uint8
    assert set(got.tolist()) == set(range(1, 8))  # never an empty (zero) slot, every filled one reachable
    assert not bool(rb.can_sample(buf, 8)) and bool(rb.can_sample(buf, 7))
    assert int(np.asarray(rb.sample(buf, jnp.array([0.9999999]))["x"])[0]) == 7


def test_replay_under_vmap():
    bufs = jax.vmap(lambda _: rb.init({"x": jnp.zeros(())}, 4))(jnp.arange(3))
    bufs = jax.vmap(rb.add)(bufs, {"x": jnp.array([1.0, 2.0, 3.0])})
    np.testing.assert_array_equal(bufs.size, [1, 1, 1])
    np.testing.assert_array_equal(jax.vmap(rb.sample)(bufs, jnp.full((3, 2), 0.5))["x"], [[1, 1], [2, 2], [3, 3]])


def test_one_hot_codec_is_lossless_on_every_env_observation():
    """Replay rows store one integer per one-hot block; decoding gives back the env's exact features for
    random states of the team env and of a sub-task env with the cell input."""
    from jaxusar.algos import subpolicies as sp
    env = envs.make("two_rooms")
    rng = np.random.default_rng(0)
    n = 64
    states = envs.EnvState(agent_pos=jnp.asarray(rng.integers(0, [env.height, env.width], (n, env.n_agents, 2)), jnp.int32),
                           agent_dir=jnp.asarray(rng.integers(0, 4, (n, env.n_agents)), jnp.int32),
                           triaged=jnp.asarray(rng.integers(0, 2, (n, env.n_victims)), bool),
                           t=jnp.zeros((n,), jnp.int32))
    task = sp.SubtaskEnv(env, 50, features="cell")
    cases = [(env.obs_blocks, jax.vmap(env.observe)(states)),
             (task.obs_blocks, jax.vmap(task.observe)(states.agent_pos[:, 0], states.agent_dir[:, 0],
                                                        states.triaged[:, 0]))]
    for blocks, obs in cases:
        codec = rb.OneHotCodec(blocks)
        codes = codec.encode(obs)
        assert codes.shape == (n, len(blocks)) and codes.dtype == (jnp.uint16 if max(blocks) > 255 else jnp.uint8)
        np.testing.assert_array_equal(codec.decode(codes), obs)
    wide = rb.OneHotCodec((300, 2))  # a block wider than 255 (the cell input of a 20 x 30 map): uint16
    obs = jnp.concatenate([jax.nn.one_hot(jnp.array([0, 299, 7]), 300), jax.nn.one_hot(jnp.array([1, 0, 1]), 2)], -1)
    assert wide.encode(obs).dtype == jnp.uint16
    np.testing.assert_array_equal(wide.decode(wide.encode(obs)), obs)
    zeros = rb.OneHotCodec((3, 1, 2))  # an all-zero block is stored as its width, a flag as its value
    np.testing.assert_array_equal(zeros.encode(jnp.array([0, 0, 0, 1, 0, 1.0])), [3, 1, 1])
    np.testing.assert_array_equal(zeros.encode(jnp.array([0, 1, 0, 0, 1, 0.0])), [1, 0, 0])
    np.testing.assert_array_equal(zeros.decode(zeros.encode(jnp.array([0, 0, 0, 1, 0, 1.0]))), [0, 0, 0, 1, 0, 1])
    with pytest.raises(ValueError, match="sum to 6"):
        zeros.encode(jnp.zeros(5))


def test_compact_rows_train_bit_identically_to_full_rows():
    """The same trials with observations stored as uint8 features or as one-hot indices: every number
    equal, parameters included; the compact row is a fraction of the full one."""
    from jaxusar.core.learners import dqn_target
    _, _, tr = _tiny_trainer(episodes=30)
    env, cfg = tr.env, tr.learner.cfg
    keys = jax.random.split(jax.random.PRNGKey(5), 2)
    compact = tr.train(keys)
    full_learner = IndependentDQN(env.obs_dim, 4, env.n_agents, cfg, dqn_target(cfg))
    tr_full = Trainer(env, full_learner, tr.cfg, learning_starts=cfg.learning_starts, train_every=cfg.train_every,
                      optimal_steps=tr.optimal_steps)
    full = tr_full.train(keys)
    a, b = tr.results(compact), tr_full.results(full)
    for name in ("train_return", "train_length", "test_return", "test_length", "best_test"):
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    for x, y in zip(jax.tree.leaves(compact.trials.learner.params), jax.tree.leaves(full.trials.learner.params)):
        np.testing.assert_array_equal(x, y)
    one = lambda st: jax.tree.map(lambda x: x[0, 0], st.trials.learner.replay)
    assert rb.row_bytes(one(compact)) + 2 * (env.obs_dim - len(env.obs_blocks)) == rb.row_bytes(one(full))


def _decode_single(env, obs):
    """Inverse of env.observe for a one-agent env: (pos, dir, triaged)."""
    h, w = env.height, env.width
    obs = np.asarray(obs)
    return (np.array([[obs[:h].argmax(), obs[h:h + w].argmax()]]), np.array([obs[h + w:h + w + 4].argmax()]),
            obs[h + w + 4:].astype(bool))


def test_sampled_next_obs_is_the_step_after_obs():
    """Rows from a real training run: re-stepping the env from obs with the stored action gives next_obs."""
    env = envs.make(envs.load_layout("two_rooms").subset(agents=[1]), horizon=30)
    cfg = config.load(sets=["train.episodes=40", "train.test_every=20", "train.chunk_steps=400",
                            "dqn.learning_starts=100", "dqn.buffer_capacity=300"])
    learner = iql.make_learner(env, cfg.dqn)
    trainer = Trainer(env, learner, cfg.train, learning_starts=100, train_every=4, optimal_steps=17)
    state = trainer.train(jax.random.split(jax.random.PRNGKey(3), 1))
    buf = jax.tree.map(lambda x: x[0, 0], state.trials.learner.replay)  # trial 0, learner 0
    batch = learner.dqn.expand(rb.sample(buf, jax.random.uniform(jax.random.PRNGKey(1), (64,))))
    step = jax.jit(env.step)
    for i in range(64):
        pos, d, tri = _decode_single(env, batch["obs"][i])
        s = envs.EnvState(jnp.asarray(pos, jnp.int32), jnp.asarray(d, jnp.int32), jnp.asarray(tri), jnp.int32(0))
        nxt, _, r, _, info = step(None, s, jnp.asarray([batch["action"][i]]))
        np.testing.assert_array_equal(nxt, batch["next_obs"][i])
        assert float(r) == float(batch["reward"][i])
        assert bool(info["terminated"]) == bool(batch["terminal"][i])


# -- target rules --------------------------------------------------------------------------------------
def test_q_learning_target_hand_computed():
    r = jnp.array([1.0, 0.0, 5.0])
    disc = jnp.array([0.9, 0.5, 0.0])
    q = jnp.array([[1.0, 3.0], [-2.0, -1.0], [100.0, 0.0]])
    np.testing.assert_allclose(ql.q_learning_target(r, disc, q), [1 + 0.9 * 3, -0.5, 5.0])
    valid = jnp.array([[True, False], [True, True], [True, True]])
    np.testing.assert_allclose(ql.q_learning_target(r, disc, q, valid), [1 + 0.9 * 1, -0.5, 5.0])


def test_double_q_target_uses_online_argmax_and_target_value():
    r, disc = jnp.array([0.0]), jnp.array([1.0])
    q_value = jnp.array([[10.0, 20.0, 30.0]])
    q_select = jnp.array([[5.0, 0.0, 1.0]])
    np.testing.assert_allclose(ql.double_q_learning_target(r, disc, q_value, q_select), [10.0])
    mask = jnp.array([[False, True, True]])
    np.testing.assert_allclose(ql.double_q_learning_target(r, disc, q_value, q_select, mask), [30.0])


def _rows(rewards, gammas, terminal, done):
    """A replay holding one row per step, in time order; next_obs[i] = i + 1 marks the bootstrap row."""
    n = len(rewards)
    buf = rb.init({"reward": jnp.zeros(()), "gamma": jnp.zeros(()), "terminal": jnp.zeros((), bool),
                   "done": jnp.zeros((), bool), "next_obs": jnp.zeros((), jnp.int32), "obs": jnp.zeros((), jnp.int32)}, 8)
    for i in range(n):
        buf = rb.add(buf, {"reward": rewards[i], "gamma": gammas[i], "terminal": terminal[i], "done": done[i],
                           "next_obs": i + 1, "obs": i})
    return buf


def _at(buf, i):
    """Uniforms that draw row i (of size rows)."""
    return jnp.array([(i + 0.5) / int(buf.size)])


def test_n_step_returns_hand_computed():
    """Rows 0-2 one episode cut by a time limit after row 2, rows 3-4 an episode solved at row 4, row 5
    the newest; row 1 is an SMDP step of its own discount 0.5 (gamma^k)."""
    g = 0.9
    r = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0]
    gam = [g, 0.5, g, g, g, g]
    term = [False, False, False, False, True, False]
    done = [False, False, True, False, True, False]
    buf = _rows(r, gam, term, done)
    cases = {  # row: (n, return, bootstrap discount, bootstrap row)
        0: (3, 1 + g * 2 + g * 0.5 * 4, g * 0.5 * g, 2),   # three rows, bootstrap after the cut's true next obs
        1: (3, 2 + 0.5 * 4, 0.5 * g, 2),                    # stops at the time-limit cut: never crosses into row 3
        3: (3, 8 + g * 16, 0.0, 4),                         # the task is solved at row 4: no bootstrap
        4: (1, 16.0, 0.0, 4),
        5: (3, 32.0, g, 5),                                 # the newest row: nothing after it yet
        2: (1, 4.0, g, 2),                                  # n = 1 is the row itself, truncation bootstraps
    }
    for i, (n, ret, disc, last) in cases.items():
        b = rb.sample_returns(buf, _at(buf, i), n)
        np.testing.assert_allclose(float(b["reward"][0]), ret, rtol=1e-6)
        np.testing.assert_allclose(float(b["discount"][0]), disc, rtol=1e-6)
        assert int(b["next_obs"][0]) == last + 1 and int(b["obs"][0]) == i


def test_n_step_returns_stop_before_an_exploring_action():
    """With ``extend``, the return from row i never runs through a later row whose action explored
    (row i's own action may explore: it is the one being valued)."""
    g = 0.9
    buf = _rows([1.0, 2.0, 4.0, 8.0], [g] * 4, [False] * 4, [False] * 4)
    greedy = jnp.array([False, True, False, True] + [True] * 4)
    b = rb.sample_returns(buf, _at(buf, 0), 3, lambda k: greedy[k])  # rows 0, 1; row 2 explored
    np.testing.assert_allclose([float(b["reward"][0]), float(b["discount"][0])], [1 + g * 2, g * g], rtol=1e-6)
    assert int(b["next_obs"][0]) == 2
    b = rb.sample_returns(buf, _at(buf, 2), 3, lambda k: greedy[k])  # row 2 explored itself: rows 2, 3
    np.testing.assert_allclose(float(b["reward"][0]), 4 + g * 8, rtol=1e-6)


def test_learners_flag_greedy_actions_for_n_step_returns():
    env = tiny_env()
    learner = iql.make_learner(env, DQNConfig(hidden=(8,), n_step=3, n_step_cut_exploring=True, batch_size=4,
                                              buffer_capacity=8))
    obs, _ = env.reset(jax.random.PRNGKey(0))
    tr = {"obs": obs, "action": jnp.array([0, 1], jnp.int32), "reward": jnp.float32(0), "next_obs": obs,
          "done": jnp.bool_(False), "info": {"terminated": jnp.bool_(False)}, "carry": learner.init_carry(),
          "next_carry": learner.init_carry()}
    st = learner.init(jax.random.PRNGKey(1), tr)
    greedy, _ = learner.greedy_act(st.params, obs, None)
    tr["action"] = jnp.stack([greedy[0], (greedy[1] + 1) % 4])
    st = learner.observe(st, tr)
    np.testing.assert_array_equal(st.replay.rows["greedy"][:, 0], [True, False])


def test_n_step_returns_cut_where_the_current_target_net_would_act_otherwise():
    """``n_step_cut_greedy``: the return stops before a stored action that is not the target net's argmax
    now (whatever the acting params were); without the option it runs all n rows."""
    g = 0.5
    obs = jnp.eye(4, dtype=jnp.float32)
    def run(cut, flip):  # rows 0-3; row ``flip``'s action is the non-greedy one
        cfg = DQNConfig(hidden=(8,), batch_size=1, buffer_capacity=8, n_step=3, gamma=g, n_step_cut_greedy=cut)
        dqn = ql.DQN(4, 2, cfg, lambda b, qt, qo: b["reward"])
        row = lambda i, a: {"obs": obs[i], "action": jnp.int32(a), "reward": jnp.float32(2.0 ** i),
                            "next_obs": obs[(i + 1) % 4], "terminal": jnp.bool_(False), "done": jnp.bool_(False)}
        st = dqn.init(jax.random.PRNGKey(3), row(0, 0))
        greedy = np.asarray(jnp.argmax(dqn.q_values(st.target_params, obs), -1))
        for i in range(4):
            st = dqn.add(st, row(i, greedy[i] if i != flip else 1 - greedy[i]))
        b = dqn.sample(st, jnp.array([0.5 / 4]))  # row 0
        return float(b["reward"][0]), float(b["discount"][0]), int(jnp.argmax(b["next_obs"][0]))
    np.testing.assert_allclose(run(True, 2), (1 + g * 2, g * g, 2), rtol=1e-6)   # stops before row 2
    np.testing.assert_allclose(run(True, 1), (1, g, 1), rtol=1e-6)               # one step: row 1 explored
    np.testing.assert_allclose(run(True, 0), (1 + g * 2 + g * g * 4, g ** 3, 3), rtol=1e-6)  # row 0 is valued
    np.testing.assert_allclose(run(False, 1), (1 + g * 2 + g * g * 4, g ** 3, 3), rtol=1e-6)


def test_n_step_returns_follow_the_ring_and_stop_at_the_newest_row():
    """Capacity 8, 11 rows written: the oldest kept row is 3 (slot 3); its successors wrap to slots 0-2,
    and the newest (row 10, slot 2) ends every return."""
    buf = rb.init({"reward": jnp.zeros(()), "gamma": jnp.zeros(()), "terminal": jnp.zeros((), bool),
                   "done": jnp.zeros((), bool), "next_obs": jnp.zeros((), jnp.int32)}, 8)
    for i in range(11):
        buf = rb.add(buf, {"reward": float(i), "gamma": 1.0, "terminal": False, "done": False, "next_obs": i + 1})
    slot = lambda s: jnp.array([(s + 0.5) / 8])
    b = rb.sample_returns(buf, slot(7), 4)  # row 7, then rows 8, 9, 10 in slots 0, 1, 2
    assert float(b["reward"][0]) == 7 + 8 + 9 + 10 and int(b["next_obs"][0]) == 11
    b = rb.sample_returns(buf, slot(1), 4)  # row 9: only row 10 after it
    assert float(b["reward"][0]) == 9 + 10 and int(b["next_obs"][0]) == 11


def test_epsilon_schedule_and_greedy():
    cfg = DQNConfig(eps_start=1.0, eps_end=0.1, eps_decay_steps=100)
    np.testing.assert_allclose([ql.linear_epsilon(cfg, s) for s in (0, 50, 100, 1000)], [1.0, 0.55, 0.1, 0.1],
                               rtol=1e-6)
    q = jnp.array([0.0, 5.0, 1.0, 2.0])
    assert int(ql.epsilon_greedy(q, 0.0, 0.5, 0.0)) == 1
    valid = jnp.array([True, False, True, False])
    # exploring picks uniformly among valid actions only
    picks = [int(ql.epsilon_greedy(q, 1.0, 0.0, u, valid)) for u in np.linspace(0, 0.999, 50)]
    assert set(picks) == {0, 2} and 20 <= picks.count(0) <= 30
    assert int(ql.epsilon_greedy(q, 0.0, 0.9, 0.0, valid)) == 2  # greedy over valid only
    assert int(ql.epsilon_greedy(q, 0.0, 0.9, 0.0, valid, mask_greedy=False)) == 1  # greedy over all


def test_hard_target_copy_period():
    cfg = DQNConfig(hidden=(8,), batch_size=4, buffer_capacity=16, target_update_every=3)
    dqn = ql.DQN(3, 2, cfg, lambda b, qt, qo: b["reward"])
    row = {"obs": jnp.ones(3), "action": jnp.int32(0), "reward": jnp.float32(1.0), "next_obs": jnp.ones(3),
           "terminal": jnp.bool_(False), "done": jnp.bool_(False)}
    st = dqn.init(jax.random.PRNGKey(0), row)
    for _ in range(4):
        st = dqn.add(st, row)
    same = lambda a, b: all(np.allclose(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
    u = jnp.full((4,), 0.3)
    st = dqn.update(st, u)
    assert not same(st.params, st.target_params)
    st = dqn.update(dqn.update(st, u), u)  # third update copies
    assert int(st.updates) == 3 and same(st.params, st.target_params)


# -- trainer -------------------------------------------------------------------------------------------
def _tiny_trainer(episodes=60, **sets):
    cfg = config.load(sets=[f"train.episodes={episodes}", "train.test_every=10", "train.chunk_steps=400",
                            "dqn.learning_starts=100", "dqn.eps_decay_steps=1500", "dqn.hidden=[32]",
                            "dqn.target_update_every=50"] + [f"{k}={v}" for k, v in sets.items()])
    env = tiny_env()
    opt = planning.optimal_team_steps(env)
    tr = Trainer(env, iql.make_learner(env, cfg.dqn), cfg.train, learning_starts=cfg.dqn.learning_starts,
                 train_every=cfg.dqn.train_every, optimal_steps=opt)
    return env, opt, tr


def test_trial_equals_running_alone_and_is_deterministic():
    _, _, tr = _tiny_trainer(episodes=40)
    keys = jax.random.split(jax.random.PRNGKey(7), 3)
    together = tr.results(tr.train(keys))
    alone = tr.results(tr.train(keys[1:2]))
    again = tr.results(tr.train(keys))
    for name in ("train_return", "train_length", "test_return", "test_length"):
        np.testing.assert_array_equal(together[name][1], alone[name][0], err_msg=name)
        np.testing.assert_array_equal(together[name], again[name], err_msg=name)
    assert together["episodes_to_optimal"] == again["episodes_to_optimal"]
    # different keys give different trials
    assert not np.array_equal(together["train_length"][0], together["train_length"][2])


def test_finished_trials_stop_running_and_no_result_changes():
    """Between chunks, once at most half the trials lack episodes, only those run (a power-of-two batch,
    padded); every number equals the run that steps all trials to the end (train.drop_finished=false), best
    params included."""
    _, _, tr = _tiny_trainer(episodes=40, **{"train.chunk_steps": 100})
    keys = jax.random.split(jax.random.PRNGKey(2), 8)
    calls = []
    run_lanes = tr._lanes_chunk
    tr._lanes_chunk = lambda state, lanes: calls.append(lanes) or run_lanes(state, lanes)
    dropped = tr.train(keys)
    _, _, kept = _tiny_trainer(episodes=40, **{"train.chunk_steps": 100, "train.drop_finished": "false"})
    kept_calls = []
    kept._lanes_chunk = lambda state, lanes: kept_calls.append(lanes) or run_lanes(state, lanes)
    full = kept.train(keys)
    assert not kept_calls  # the config's drop_finished=false reached the trainer: no smaller batch ran
    assert calls and all(len(c) < 8 and len(c) & (len(c) - 1) == 0 for c in calls), calls
    assert [c.tolist() for c in calls] == [[1, 5, 6, 8]]  # trials 1, 5, 6 and a padding lane (8: writes dropped)
    a, b = tr.results(dropped), tr.results(full)
    for name in ("train_return", "train_length", "test_return", "test_length", "best_test", "env_steps"):
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert a["episodes_to_optimal"] == b["episodes_to_optimal"]
    for x, y in zip(jax.tree.leaves(a["best_params"]), jax.tree.leaves(b["best_params"])):
        np.testing.assert_array_equal(x, y)


def test_finished_trials_drop_to_the_next_smaller_power_of_two():
    """A batch that is not a power of two (office: 128 lanes, two_rooms at 64 trials: 384) compacts as soon
    as the trials still running fit a smaller power of two, padded with an index past the last trial."""
    _, _, tr = _tiny_trainer(episodes=40)
    state = tr.init(jax.random.split(jax.random.PRNGKey(0), 6))
    for live, want in [([1, 1, 1, 1, 1, 0], None), ([1, 1, 0, 1, 0, 0], [0, 1, 3, 6]), ([0, 0, 0, 1, 0, 0], [3])]:
        tr._live = lambda episodes, first, mask=np.array(live, bool): mask
        got = tr.lanes_to_run(state)
        assert (None if got is None else got.tolist()) == want, live


def test_batch_buckets_are_powers_of_two_below_24_and_waste_at_most_a_third_above():
    from jaxusar.core.trainer import batch_bucket

    assert [batch_bucket(n) for n in (1, 2, 3, 5, 9, 15, 16, 17, 24, 25, 33, 48, 49, 97, 133, 184)] == \
        [1, 2, 4, 8, 16, 16, 16, 24, 24, 32, 48, 48, 64, 128, 192, 192]
    for n in range(1, 1000):
        size = batch_bucket(n)
        assert size >= n and (size & (size - 1) == 0 if size < 24 else 3 * (size - n) <= size), n
    # few programs: 1, 2, 4, 8, 16, 24, 32, 48, ..., 256, 384
    assert sorted({batch_bucket(n) for n in range(1, 385)}) == [1, 2, 4, 8, 16, 24, 32, 48, 64, 96, 128, 192,
                                                                 256, 384]


def test_stop_at_optimal_keeps_every_number_up_to_the_stop_and_runs_less():
    """train.stop_at_optimal: a trial stops after the chunk of its first optimal test. Its episodes to
    optimal, kept params and curves up to the stop equal the full run's; the rest is nan, and it ran
    fewer env steps (counted steps: with drop_finished on, it also stops costing, as a finished trial)."""
    sets = {"dqn.gamma": 0.9, "dqn.lr": 0.001, "dqn.train_every": 1, "train.chunk_steps": 200}
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    _, _, full_tr = _tiny_trainer(episodes=300, **sets)
    _, _, stop_tr = _tiny_trainer(episodes=300, **sets, **{"train.stop_at_optimal": "true"})
    stop_tr.drop_finished = False  # a trial left alone runs in a batch of 1, where XLA may round otherwise
    full, stop = full_tr.results(full_tr.train(keys)), stop_tr.results(stop_tr.train(keys))
    assert stop["episodes_to_optimal"] == full["episodes_to_optimal"] and None not in full["episodes_to_optimal"]
    for x, y in zip(jax.tree.leaves(stop["best_params"]), jax.tree.leaves(full["best_params"])):
        np.testing.assert_array_equal(x, y)
    for k, eto in enumerate(full["episodes_to_optimal"]):
        ran = int(np.sum(~np.isnan(stop["train_length"][k])))
        assert eto <= ran < 300 and np.isnan(stop["train_length"][k, ran:]).all()
        np.testing.assert_array_equal(stop["train_length"][k, :ran], full["train_length"][k, :ran])
        tests = ran // 10
        np.testing.assert_array_equal(stop["test_length"][k, :tests], full["test_length"][k, :tests])
        assert np.isnan(stop["test_length"][k, tests:]).all()
        assert stop["env_steps"][k] < full["env_steps"][k]


def test_iql_learns_tiny_map_and_best_params_replay():
    # gamma 0.9: with no step penalty, a strong time preference is what makes the shortest plan best
    env, opt, tr = _tiny_trainer(episodes=300, **{"dqn.gamma": 0.9, "dqn.lr": 0.001, "dqn.train_every": 1})
    assert opt == 2  # agent 0 triages ahead at once; agent 1 turns right, then triages
    res = tr.results(tr.train(jax.random.split(jax.random.PRNGKey(0), 2)))
    assert all(e is not None and e <= 300 for e in res["episodes_to_optimal"]), res["episodes_to_optimal"]
    for k in range(2):
        # the kept best params reproduce the best test, which is the best of all recorded tests
        params = jax.tree.map(lambda x: x[k], res["best_params"])
        ret, length, terminated, optimal = tr.greedy_episode(params, jax.random.PRNGKey(0))
        assert int(optimal) == opt
        assert float(ret) == res["best_return"][k] == res["test_return"][k].max() == 200.0
        assert int(length) == res["best_length"][k] == opt and bool(terminated)
        first = res["episodes_to_optimal"][k] // 10 - 1
        assert res["test_optimal"][k][first] and not res["test_optimal"][k][:first].any()
        assert res["episodes_to_solved"][k] <= res["episodes_to_optimal"][k]  # optimal implies solved
        assert (res["test_solved"][k] == (res["test_return"][k] == 200.0)).all()
    assert res["train_length"].shape == (2, 300) and res["test_return"].shape == (2, 30)


def test_trainer_rejects_tests_closer_than_updates():
    env = tiny_env()
    cfg = TrainConfig(episodes=10, test_every=1, chunk_steps=100)
    with pytest.raises(ConfigError, match="test_every"):
        Trainer(env, iql.make_learner(env, DQNConfig()), cfg, learning_starts=0, train_every=8, optimal_steps=2)


def test_more_tests_in_a_chunk_than_snapshot_slots_are_all_recorded():
    """40 greedy tests fall in one chunk and only 8 snapshot slots exist: full slots are evaluated
    mid-chunk, so every test is recorded (a lost one would keep its initial 0 steps)."""
    env = tiny_env()
    cfg = config.load(sets=["train.episodes=40", "train.test_every=1", "train.chunk_steps=4000", "dqn.train_every=1",
                            "dqn.learning_starts=1000", "dqn.hidden=[8]"])
    tr = Trainer(env, iql.make_learner(env, cfg.dqn), cfg.train, learning_starts=1000, train_every=1, optimal_steps=2)
    assert tr.n_slots == 8 and tr.n_tests == 40
    state = tr.train(jax.random.split(jax.random.PRNGKey(0), 2))
    assert int(state.chunk) == 1
    r = tr.results(state)
    assert (r["test_length"] > 0).all(), r["test_length"]


def test_iql_learners_share_nothing():
    env = tiny_env()
    learner = iql.make_learner(env, DQNConfig(hidden=(8,), buffer_capacity=64))
    assert isinstance(learner, IndependentDQN) and learner.n == env.n_agents
    obs, s = env.reset(None)
    tr = {"obs": obs, "action": jnp.array([0, 3]), "reward": jnp.float32(0), "next_obs": obs,
          "done": jnp.bool_(False), "info": {"terminated": jnp.bool_(False)}}
    st = learner.init(jax.random.PRNGKey(0), tr)
    leaves = jax.tree.leaves(st.params)
    assert all(x.shape[0] == 2 for x in leaves)
    assert not np.allclose(leaves[-1][0], leaves[-1][1])  # separately initialised networks
    st = learner.observe(st, tr)
    np.testing.assert_array_equal(st.replay.rows["action"][:, 0], [0, 3])  # each stores its own action


# -- config --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sets, match", [
    (["dqn.gamma=0"], "dqn.gamma"), (["dqn.gamma=1.5"], "dqn.gamma"),
    (["dqn.buffer_capacity=16", "dqn.batch_size=32"], "buffer_capacity"),
    (["train.episodes=-3"], "train.episodes"), (["dqn.bogus=1"], "dqn.bogus"),
    (["train.episodes=ten"], "train.episodes"), (["dqn.hidden=64"], "dqn.hidden"),
    (["dqn.double_dqn=1"], "double_dqn"), (["nokey"], "key=value"), (["dqn.loss=l1"], "dqn.loss"),
    (["algo=hierarchical", "hierarchical.coordinator.episodes=4", "hierarchical.coordinator.test_every=5"],
     r"hierarchical.coordinator.test_every=5 exceeds hierarchical.coordinator.episodes=4: no team test"),
])
def test_config_errors_name_the_key(sets, match):
    with pytest.raises(ConfigError, match=match):
        config.load(sets=sets)


@pytest.mark.parametrize("sets, match", [
    (["dqn.n_step=0"], r"dqn.n_step=0 is out of range \(.*>= 1"),
    (["dqn.gradient_steps=0"], r"dqn.gradient_steps=0 is out of range \(.*>= 1"),
    (["dqn.train_every=0"], r"dqn.train_every=0 is out of range \(.*>= 1"),
    (["dqn.tau=0"], r"dqn.tau=0.0 is out of range \(in \(0, 1\]"),
    (["dqn.tau=1.5"], r"dqn.tau=1.5 is out of range \(in \(0, 1\]"),
    (["hierarchical.focus_starts=1.5"], r"hierarchical.focus_starts=1.5 is out of range \(.*in \[0, 1\]"),
    (["hierarchical.focus_starts=-0.1"], r"hierarchical.focus_starts=-0.1 is out of range"),
    (["dqn.reward_scale=0"], r"dqn.reward_scale=0.0 is out of range \(> 0"),
    (["dqn.reward_scale=-1"], r"dqn.reward_scale=-1.0 is out of range"),
    (["dqn.lr=0"], r"dqn.lr=0.0 is out of range \(Adam learning rate, > 0"),
    (["dqn.lr_schedule=step"], r"dqn.lr_schedule='step' is out of range \(constant, linear or cosine"),
    (["dqn.lr_decay_updates=0"], r"dqn.lr_decay_updates=0 is out of range"),
    (["dqn.lr_schedule=linear", "dqn.lr_end=0.1"], r"dqn.lr_end=0.1 is above dqn.lr=0.0005.*\(0, lr\]"),
    (["hierarchical.coordinator.n_step=0"], r"hierarchical.coordinator.n_step=0 is out of range"),
    (["hierarchical.coordinator.gradient_steps=0"], r"hierarchical.coordinator.gradient_steps=0 is out of range"),
    (["hierarchical.subpolicy_features=pixels"], r"hierarchical.subpolicy_features='pixels' is out of range"),
    (["hierarchical.navigate_start=anywhere"], r"hierarchical.navigate_start='anywhere' is out of range"),
    (["hierarchical.navigation=goals"], r"hierarchical.navigation='goals' is out of range.*goal"),
    (["hierarchical.coordinator.termination=first"], r"hierarchical.coordinator.termination='first' is out of range"),
    (["hierarchical.coordinator.features=pixels"], r"hierarchical.coordinator.features='pixels' is out of range"),
    (["hierarchical.coordinator.block_patience=-1"], r"hierarchical.coordinator.block_patience=-1 is out of range"),
])
def test_new_core_options_are_checked_before_anything_compiles(sets, match):
    """Each sample-efficiency option: an error naming the key, the value and the valid range."""
    with pytest.raises(ConfigError, match=match):
        config.load(sets=sets)


def test_option_critic_refuses_n_step_returns():
    from jaxusar.algos import option_critic

    with pytest.raises(ConfigError, match="dqn.n_step=3.*use dqn.n_step=1"):
        option_critic.make_learner(tiny_env(), DQNConfig(n_step=3))


def test_lr_schedules_decay_to_lr_end():
    for kind in ("linear", "cosine"):
        sched = ql.learning_rate(DQNConfig(lr=1e-3, lr_schedule=kind, lr_end=1e-4, lr_decay_updates=100))
        assert float(sched(0)) == pytest.approx(1e-3) and float(sched(100)) == pytest.approx(1e-4)
        assert float(sched(1000)) == pytest.approx(1e-4) and 1e-4 < float(sched(50)) < 1e-3
    assert ql.learning_rate(DQNConfig(lr=1e-3)) == 1e-3


def test_gradient_steps_make_that_many_updates_per_learning_step():
    env = tiny_env()
    counts = []
    for g in (1, 3):
        cfg = DQNConfig(hidden=(8,), batch_size=4, learning_starts=0, train_every=2, gradient_steps=g)
        trainer = Trainer(env, iql.make_learner(env, cfg), TrainConfig(episodes=2, test_every=1, chunk_steps=40),
                          learning_starts=0, train_every=2, gradient_steps=g, optimal_steps=4)
        state = trainer.init(jax.random.split(jax.random.PRNGKey(0), 2))
        trainer.compile(state)
        state = trainer.run_chunk(state)
        counts.append(np.asarray(state.trials.learner.updates))
    np.testing.assert_array_equal(counts[1], 3 * counts[0])
    assert counts[0].min() == 20  # 40 env steps, a learning step every 2


def test_config_file_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("train:\n  episodes: 10\n  speed: 3\n")
    with pytest.raises(ConfigError, match="train.speed"):
        config.load(bad)
    with pytest.raises(ConfigError, match="does not exist"):
        config.load(tmp_path / "missing.yaml")
    bad.write_text("train: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        config.load(bad)


def test_shipped_configs_equal_the_algorithm_defaults():
    """configs/<algo>.yaml spell out exactly what `jaxusar train <algo>` runs without --config."""
    from pathlib import Path

    from jaxusar import algos

    paths = sorted((Path(__file__).parents[1] / "configs").glob("*.yaml"))
    assert paths
    for path in paths:
        cfg = config.load(path)
        assert cfg == config.load(defaults=algos.defaults(cfg.algo)), path.name


def test_episodes_to_optimal_in_words():
    from jaxusar.experiments.stats import in_words

    assert in_words([None, None], 5000) == "optimal in 0 of 2 trials (never within 5,000 episodes)"
    assert in_words([1200, None, 300], 5000) == ("optimal in 2 of 3 trials, after 300, 1,200 episodes; never within "
                                                 "5,000 in the other 1; median 1,200")
    assert in_words([10, None, None], 100) .endswith("median > 100")


def test_one_hot_input_layer_is_the_dense_layer():
    """dqn.one_hot_input: the first layer looks up kernel rows at the one-hot blocks; the same parameters
    (names, shapes, init) and, up to float rounding, the same outputs and gradients as the dense network."""
    from jaxusar.core.qlearning import MLP

    sizes = (5, 7, 4, 1, 3)
    dense, looked_up = MLP((16, 16), 4), MLP((16, 16), 4, sizes)
    key = jax.random.PRNGKey(0)
    idx = jax.random.randint(key, (32, len(sizes)), 0, jnp.asarray(sizes) + 1)  # index == width: an all-zero block
    obs = jnp.concatenate([jax.nn.one_hot(idx[:, b], n) for b, n in enumerate(sizes)], -1)
    params = dense.init(key, obs[0])
    chex.assert_trees_all_equal(params, looked_up.init(key, obs[0]))
    np.testing.assert_allclose(looked_up.apply(params, obs), dense.apply(params, obs), rtol=1e-5, atol=1e-6)
    loss = lambda net: (lambda p: jnp.sum(net.apply(p, obs) ** 2))
    chex.assert_trees_all_close(jax.grad(loss(looked_up))(params), jax.grad(loss(dense))(params), rtol=1e-5,
                                atol=1e-6)
    with pytest.raises(ValueError, match="one_hot_input needs"):
        ql.DQN(sum(sizes), 4, config.DQNConfig(one_hot_input=True), None)


def test_uniform_row_is_the_row_jax_random_uniform_draws_bit_for_bit():
    """The trainer draws an iteration's update noise alone (``uniform_row``); it must be exactly the row of
    the whole chunk's ``jax.random.uniform`` (the numbers before this was a memory saving), for raw and typed
    keys and any row, else every result on the default seeds would move."""
    from jaxusar.core.trainer import uniform_row

    for key in (jax.random.PRNGKey(7), jax.random.fold_in(jax.random.PRNGKey(0), 3), jax.random.key(11)):
        full = jax.random.uniform(key, (6, 2, 3, 5))
        for row in (0, 1, 5):
            got = jax.jit(uniform_row, static_argnums=1)(key, (2, 3, 5), jnp.uint32(row))
            np.testing.assert_array_equal(np.asarray(got), np.asarray(full[row]))
