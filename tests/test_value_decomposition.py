"""VDN and QMIX (jaxusar/algos/vdn.py, qmix.py) on the shared core (``core.learners.TeamDQN``).

What would catch a wrong implementation: one agent's VDN is one DQN (the same params after the same training
run: the same updates on the same batches); QMIX's mixer is monotonic in every agent's Q at random inputs and
params, and does condition on the state; both find a coordinated optimum that independent learners provably
miss (every seed); both train from the command line on a USAR map, in both observations.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxusar import algos, config, envs, planning
from jaxusar.algos import qmix, vdn
from jaxusar.cli import main
from jaxusar.core.learners import IndependentDQN, TeamDQN, dqn_target
from jaxusar.core.trainer import Trainer


@pytest.fixture(autouse=True, scope="module")
def cheap_compiles():
    """XLA's least optimising compiles for this file (nothing here is timed), then the setting as it was."""
    before = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", True)
    yield
    jax.config.update("jax_disable_most_optimizations", before)


def test_the_registry_lists_both():
    assert {"vdn", "qmix"} <= set(algos.registry())
    assert algos.algorithm("vdn") is vdn and algos.algorithm("qmix") is qmix


# -- VDN with one agent is DQN ---------------------------------------------------------------------------
def test_vdn_with_one_agent_is_one_dqn():
    """A sum of one agent's Q is that agent's Q: the same training run (same keys, the trainer's same acting
    and batch noise) gives IQL's one learner and VDN's one agent the same params, replay and episodes."""
    env = envs.make(envs.load_layout("two_rooms").subset(agents=[1]), horizon=30)
    cfg = config.load(sets=["train.episodes=16", "train.test_every=8", "train.chunk_steps=240", "dqn.hidden=[16]",
                            "dqn.learning_starts=40", "dqn.train_every=4", "dqn.batch_size=8",
                            "dqn.target_update_every=10", "dqn.eps_decay_steps=300"])
    keys = jax.random.split(jax.random.PRNGKey(5), 2)
    out = {}
    for name in ("iql", "vdn"):
        learner = algos.algorithm(name).make_learner(env, cfg.dqn)
        tr = Trainer(env, learner, cfg.train, learning_starts=cfg.dqn.learning_starts, train_every=cfg.dqn.train_every,
                     optimal_steps=17)
        state = tr.train(keys)
        out[name] = (tr.results(state), state.trials.learner)
    (r_iql, l_iql), (r_vdn, l_vdn) = out["iql"], out["vdn"]
    assert int(np.asarray(l_vdn.updates).min()) > 50  # it did learn
    for name in ("train_return", "train_length", "test_return", "test_length"):
        np.testing.assert_array_equal(r_iql[name], r_vdn[name], err_msg=name)
    assert jax.tree.leaves(l_vdn.params["mixer"]) == []  # a sum has no parameters
    # IQL's params: [trials, learner=1, ...]; VDN's agents: [trials, agent=1, ...]
    for a, b in zip(jax.tree.leaves(l_iql.params), jax.tree.leaves(l_vdn.params["agents"]), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(l_iql.replay.rows["obs"][:, 0], l_vdn.replay.rows["obs"])
    np.testing.assert_array_equal(l_iql.replay.rows["action"][:, 0], l_vdn.replay.rows["action"][..., 0])


# -- QMIX's mixer --------------------------------------------------------------------------------------
@pytest.mark.parametrize("n_agents,state_dim", [(2, 60), (3, 12)])
def test_the_qmix_mixer_is_monotonic_in_every_agents_q_and_conditions_on_the_state(n_agents, state_dim):
    mixer = qmix.MonotonicMixer()

    @jax.jit
    def draw(key):
        k_init, k_scale, k_q, k_s = jax.random.split(key, 4)
        params = mixer.init(k_init, jnp.zeros(n_agents), jnp.zeros(state_dim))
        # random params, not just the init: every leaf rescaled and shifted at random (signs included)
        leaves, tree = jax.tree.flatten(params)
        ks = jax.random.split(k_scale, len(leaves))
        params = jax.tree.unflatten(tree, [3.0 * jax.random.normal(k, x.shape) + x for k, x in zip(ks, leaves)])
        q = 10.0 * jax.random.normal(k_q, (256, n_agents))
        state = jax.random.bernoulli(k_s, 0.3, (256, state_dim)).astype(jnp.float32)
        grad = jax.vmap(jax.grad(mixer.apply, argnums=1), in_axes=(None, 0, 0))(params, q, state)
        # the same q under every state: the mixing depends on the state
        return grad, jax.vmap(mixer.apply, in_axes=(None, None, 0))(params, q[0], state)

    for trial in range(6):
        g, totals = map(np.asarray, draw(jax.random.PRNGKey(trial)))
        assert g.shape == (256, n_agents) and (g >= 0).all(), g.min()
        assert (g > 0).any(axis=0).all()  # every agent's Q counts somewhere
        assert np.ptp(totals) > 1e-3
    # and VDN's mixer is the plain sum
    s = vdn.SumMixer()
    np.testing.assert_allclose(s.apply({}, jnp.array([1.5, -2.0, 4.0]), jnp.zeros(5)), 3.5)


def test_teamdqn_feeds_each_agent_its_own_row_and_the_mixer_all_of_them():
    """With per-agent observations (view) agent i's network sees obs[i]; the mixer's state is the rows
    concatenated; the replay stores one team row with the joint action."""
    env = envs.make("two_rooms_rubble", observation="view")
    obs, state = jax.jit(env.reset)(None)
    learner = qmix.make_learner(env, config.load(sets=["dqn.hidden=[8]", "dqn.batch_size=4",
                                                       "dqn.buffer_capacity=8"]).dqn)
    actions = jnp.asarray([0, 1, 3], jnp.int32)
    nxt, _, r, d, info = jax.jit(env.step)(None, state, actions)
    tr = {"obs": obs, "action": actions, "reward": r, "next_obs": nxt, "done": d, "info": info,
          "carry": jnp.zeros((), jnp.int32), "next_carry": jnp.zeros((), jnp.int32)}

    @jax.jit
    def run(tr):
        st = learner.init(jax.random.PRNGKey(0), tr)
        agents = learner.policy(st)
        own = jnp.stack([learner.network.agent.apply(jax.tree.map(lambda x: x[i], agents), tr["obs"][i])
                         for i in range(3)])
        st = learner.observe(st, tr)
        team_q = learner.network.apply(st.params, tr["obs"].astype(jnp.float32))
        return learner.network.agent_q(agents, tr["obs"]), own, team_q.state, st.replay.rows, \
            learner.greedy_act(agents, tr["obs"], None)[0]

    q, own, mixer_state, rows, greedy = run(tr)
    np.testing.assert_allclose(q, own, rtol=1e-6)
    assert not np.allclose(q[0], q[1])
    np.testing.assert_array_equal(mixer_state, np.asarray(obs).reshape(-1))
    np.testing.assert_array_equal(learner.dqn.decode(rows["obs"][0]), obs)
    np.testing.assert_array_equal(rows["action"][0], actions)
    np.testing.assert_array_equal(greedy, np.argmax(own, -1))


# -- a cooperative task independent learners miss --------------------------------------------------------
PENALTY = 20.0


class TwoStepGame:
    """Two agents, two actions each, episodes of two steps (after the two-step game of Rashid et al. 2018).

    Step 1: agent 0 picks the next state, A (action 0) or B (action 1); agent 1's action does nothing. Step 2:
    in A the team gets 7 whatever they do; in B it gets 8 - PENALTY x (number of agents not playing action 1):
    8 for the coordinated joint action, additive, so a sum of per-agent values represents every reward exactly.
    Observation: the state one-hot (s0, A, B), seen by both.

    Why independent learners miss B: agent 0's value of (B, action 1) averages over its teammate's
    exploration, 8 - PENALTY * eps / 2 (= 4 at eps 0.4), below A's 7, while a learner that bootstraps from the
    team's greedy joint value (VDN, QMIX: max over the joint action of Q_tot) values B at 8.
    """

    n_agents, horizon, obs_shape, obs_blocks = 2, 2, (3,), (3,)

    def reset(self, key):
        return jax.nn.one_hot(0, 3), jnp.int32(0)

    def step(self, key, s, a):
        nxt = jnp.where(s == 0, 1 + a[0], 3).astype(jnp.int32)  # 3: the end (an all-zero observation)
        in_b = 8.0 - PENALTY * ((a[0] != 1).astype(jnp.float32) + (a[1] != 1))
        reward = jnp.where(s == 0, 0.0, jnp.where(s == 1, 7.0, in_b)).astype(jnp.float32)
        done = s != 0
        return jax.nn.one_hot(nxt, 3), nxt, reward, done, {"terminated": done}


GAME = ["train.episodes=1000", "train.test_every=250", "train.chunk_steps=2000", "dqn.hidden=[16]",
        "dqn.lr=0.001", "dqn.learning_starts=100", "dqn.train_every=1", "dqn.eps_decay_steps=1000", "dqn.eps_end=0.4",
        "dqn.buffer_capacity=500", "dqn.target_update_every=100", "dqn.reward_scale=0.1", "dqn.loss=mse"]


@pytest.mark.parametrize("name", ["iql", "vdn", "qmix"])
def test_vdn_and_qmix_coordinate_where_independent_learners_do_not(name):
    """The same budget, settings and 6 seeds for all three (the mean-squared loss: Huber's robust fit would
    discount the teammate's rare penalties and blur the effect): every IQL seed ends going to A (7), every
    VDN and QMIX seed to B with the coordinated action (8). While this was written, 24 more seeds (key 1)
    went the same way for all three, IQL's agent 0 valuing B below A by 0.08 to 0.44 (in reward_scale units)."""
    env = TwoStepGame()
    cfg = config.load(sets=GAME).dqn
    learner = {"iql": IndependentDQN(env.obs_shape, 2, 2, cfg, dqn_target(cfg), obs_blocks=env.obs_blocks),
               "vdn": TeamDQN(env.obs_shape, 2, 2, cfg, vdn.SumMixer(), obs_blocks=env.obs_blocks),
               "qmix": TeamDQN(env.obs_shape, 2, 2, cfg, qmix.MonotonicMixer(), obs_blocks=env.obs_blocks)}[name]
    tr = Trainer(env, learner, config.load(sets=GAME).train, learning_starts=cfg.learning_starts,
                 train_every=cfg.train_every, optimal_steps=2)
    state = tr.train(jax.random.split(jax.random.PRNGKey(0), 6))
    res = tr.results(state)
    policy = learner.policy(state.trials.learner)
    q_of = (lambda p, o: learner._q(p, o)) if name == "iql" else learner.network.agent_q
    q_start = np.asarray(jax.vmap(q_of, in_axes=(0, None))(policy, jax.nn.one_hot(0, 3)))  # [seed, agent, action]
    q_b = np.asarray(jax.vmap(q_of, in_axes=(0, None))(policy, jax.nn.one_hot(2, 3)))
    prefers_b = q_start[:, 0, 1] > q_start[:, 0, 0]
    assert (q_b[:, 1].argmax(-1) == 1).all()  # agent 1 learns B's action in all three: IQL's miss is agent 0's
    if name == "iql":
        assert not prefers_b.any(), q_start[:, 0]  # every seed settles for A
        assert (res["test_return"][:, -1] == 7.0).all(), res["test_return"]
    else:
        assert prefers_b.all() and (q_b.argmax(-1) == 1).all(), (q_start, q_b)
        assert (res["test_return"][:, -1] == 8.0).all(), res["test_return"]
    if name == "vdn":  # exact: agent 0 carries the whole gap, gamma * (8 - 7) * reward_scale
        np.testing.assert_allclose(q_start[:, 0, 1] - q_start[:, 0, 0], cfg.gamma * 0.1, atol=0.005)


# -- the command line ----------------------------------------------------------------------------------
@pytest.mark.parametrize("name,observation", [("vdn", "full"), ("qmix", "view")])
def test_vdn_and_qmix_train_from_the_cli(name, observation, tmp_path, capsys, monkeypatch):
    # what "optimal" means is planning's (tested in test_planning.py): skip its search here
    monkeypatch.setattr(planning, "team_reference",
                        lambda env, *args, **kw: {"steps": env.horizon, "reference": "stub", "lower_bound": 1})
    out = tmp_path / name
    argv = ["train", name, "--map", "two_rooms", "--trials", "1", "--out", str(out), "--quiet"]
    sets = ["train.episodes=2", "train.test_every=1", "train.chunk_steps=64", "env.horizon=16", "dqn.hidden=[8]",
            "dqn.batch_size=4", "dqn.buffer_capacity=64", "dqn.learning_starts=0", "dqn.train_every=4",
            f"env.observation={observation}"]
    assert main(argv + [x for s in sets for x in ("--set", s)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["algorithm"] == name and m["config"]["algo"] == name and len(m["episodes_to_optimal"]) == 1
    assert (out / "params" / "trial_0.msgpack").stat().st_size > 0
    assert f"[{name}]" in capsys.readouterr().out


def test_a_setting_value_decomposition_cannot_run_is_a_config_error(tmp_path, capsys):
    argv = ["train", "vdn", "--map", "two_rooms", "--trials", "1", "--out", str(tmp_path / "r"),
            "--set", "dqn.n_step=3", "--set", "dqn.n_step_cut_greedy=true"]
    with pytest.raises(SystemExit, match="2"):
        main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith("dqn.n_step_cut_greedy is not supported by value decomposition (vdn, qmix); "
                            "dqn.n_step_cut_exploring is"), err
    assert not (tmp_path / "r").exists()
