"""Simplified distributed option-critic: shapes, the critic's U, the termination gradient, option
switching, the runner, and learning on a tiny map."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxusar import envs
from jaxusar.algos import option_critic as oc
from jaxusar.config import DOCConfig, DQNConfig
from jaxusar.envs import parse_layout

TINY = """
.V..
.A..
..AV
....
"""
TINY_REGIONS = "H hall hall\n---\nHHHH\nHHHH\nHHHH\nHHHH\n"
SMALL = DQNConfig(hidden=(8,), batch_size=4, buffer_capacity=64, train_every=2)


def tiny_env(**kw):
    return envs.make(parse_layout(TINY, TINY_REGIONS, "tiny"), **{"horizon": 20, **kw})


def example_transition(learner, env):
    obs, state = env.reset(None)
    action = jnp.arange(1, env.n_agents + 1, dtype=jnp.int32) % envs.N_ACTIONS
    next_obs, _, reward, done, info = env.step(None, state, action)
    return {"obs": obs, "action": action, "reward": reward, "next_obs": next_obs, "done": done, "info": info,
            "carry": learner.init_carry(), "next_carry": jnp.arange(env.n_agents, dtype=jnp.int32) % 2}


def make(k=2, cfg=SMALL, **doc):
    env = tiny_env()
    learner = oc.make_learner(env, cfg, DOCConfig(actor_hidden=(8,), **doc), options=k)
    state = learner.init(jax.random.PRNGKey(0), example_transition(learner, env))
    return env, learner, state


def set_output(params, bias, layer=None):
    """A network whose last layer (or ``layer``) ignores its input: output = bias."""
    p = jax.tree.map(lambda x: x, params)
    name = layer or sorted(p["params"])[-1]
    p["params"][name] = {"kernel": jnp.zeros_like(p["params"][name]["kernel"]),
                         "bias": jnp.asarray(bias, jnp.float32).reshape(p["params"][name]["bias"].shape)}
    return p


# -- shapes ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("k", [2, 3])
def test_shapes_and_separate_agents(k):
    env, learner, state = make(k)
    obs, _ = env.reset(None)
    assert learner.critic.q_values(state.critic.params, obs).shape == (k * k,)  # centralized, joint options
    logits, beta = learner.actor_out(state.actor, obs)
    assert logits.shape == (2, k, envs.N_ACTIONS) and beta.shape == (2, k)     # K policies, K terminations / agent
    assert bool(jnp.all((beta > 0) & (beta < 1)))
    np.testing.assert_allclose(jax.nn.softmax(logits).sum(-1), 1.0, rtol=1e-6)
    kernel = state.actor["params"]["trunk_0"]["kernel"]
    assert kernel.shape[0] == 2 and not np.allclose(kernel[0], kernel[1])       # one network per agent
    noise = {name: jnp.full(shape, 0.5) for name, shape in learner.act_noise.items()}
    actions, options = learner.act(state, obs, learner.init_carry(), noise, 0)
    assert actions.shape == (2,) and options.shape == (2,) and bool(jnp.all((options >= 0) & (options < k)))
    # the replay row: the critic's action is the joint option index, the primitive actions kept beside it
    row = state.critic.replay.rows
    assert row["action"].shape == (SMALL.buffer_capacity,) and row["primitive"].shape == (SMALL.buffer_capacity, 2)
    st = learner.observe(state, example_transition(learner, env))
    assert int(st.critic.replay.rows["action"][0]) == 0 * k + 1
    np.testing.assert_array_equal(st.critic.replay.rows["primitive"][0], [1, 2])


def test_any_number_of_agents():
    """One medic or three: K^N critic outputs, one actor per medic, a joint index per replay row."""
    for env, n in ((envs.make(envs.load_layout("two_rooms").subset(agents=[1])), 1), (envs.make("four_rooms"), 3)):
        learner = oc.make_learner(env, SMALL, options=2)
        state = learner.init(jax.random.PRNGKey(0), example_transition(learner, env))
        obs, _ = env.reset(jax.random.PRNGKey(1))
        noise = {name: jnp.full(shape, 0.5) for name, shape in learner.act_noise.items()}
        actions, options = learner.act(state, obs, learner.init_carry(), noise, 0)
        assert actions.shape == (n,) and options.shape == (n,)
        assert learner.q_joint(state.critic.params, obs).shape == (2,) * n
        assert learner.actor_out(state.actor, obs)[0].shape == (n, 2, envs.N_ACTIONS)
        w = jnp.array([[1] * n, [0] * n])
        np.testing.assert_array_equal(learner.split(learner.joint(w)), w)
        assert int(learner.joint(w)[0]) == 2 ** n - 1


def test_option_critic_target_for_three_agents_sums_over_who_re_chooses():
    """U for N = 3 against a brute-force sum over the 8 sets of agents whose options end."""
    import itertools

    rng = np.random.default_rng(0)
    b, k = 5, 3
    q = rng.normal(size=(b, k, k, k)).astype(np.float32)
    beta = rng.uniform(size=(b, 3)).astype(np.float32)
    w = rng.integers(0, k, size=(b, 3))
    want = []
    for j in range(b):
        u = 0.0
        for ends in itertools.product([False, True], repeat=3):
            p = np.prod([beta[j, i] if e else 1 - beta[j, i] for i, e in enumerate(ends)])
            choices = itertools.product(*[range(k) if e else [w[j, i]] for i, e in enumerate(ends)])
            u += p * max(q[j][c] for c in choices)
        want.append(1.0 + 0.9 * u)
    got = oc.option_critic_target(jnp.ones(b), jnp.full(b, 0.9), jnp.asarray(q), jnp.asarray(beta), jnp.asarray(w))
    np.testing.assert_allclose(got, want, rtol=1e-5)
    adv = oc.termination_advantage(jnp.asarray(q), jnp.asarray(w))
    j = 0
    np.testing.assert_allclose(adv[j], [q[j][tuple(w[j])] - q[j][:, w[j, 1], w[j, 2]].max(),
                                        q[j][tuple(w[j])] - q[j][w[j, 0], :, w[j, 2]].max(),
                                        q[j][tuple(w[j])] - q[j][w[j, 0], w[j, 1], :].max()], rtol=1e-5)


# -- the critic target ------------------------------------------------------------------------------------
# Q(s', w1, w2), rows w1, columns w2: stay, re-choose agent 1 (column), agent 2 (row), both: all distinct
Q_NEXT = np.array([[1.0, 4.0, 0.0],
                   [6.0, 2.0, 7.0],
                   [8.0, 5.0, 9.0]])


def test_option_critic_target_hand_computed():
    g = 0.9
    w = jnp.array([[0, 0], [0, 0], [0, 0], [0, 0], [0, 0], [1, 2]])
    beta = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [0.5, 0.25], [1.0, 1.0]])
    q = jnp.broadcast_to(jnp.asarray(Q_NEXT), (6, 3, 3))
    r = jnp.array([1.0, 1.0, 1.0, 1.0, 1.0, 2.0])
    disc = jnp.array([g, g, g, g, g, 0.0])
    # w = (0, 0): stay Q = 1; agent 1 re-chooses over column 0 -> 8; agent 2 over row 0 -> 4; both -> 9
    u_frac = 0.5 * 0.75 * 1 + 0.5 * 0.75 * 8 + 0.5 * 0.25 * 4 + 0.5 * 0.25 * 9
    want = [1 + g * 1, 1 + g * 8, 1 + g * 4, 1 + g * 9, 1 + g * u_frac, 2.0]
    np.testing.assert_allclose(oc.option_critic_target(r, disc, q, beta, w), want, rtol=1e-6)
    # Double DQN: the maxima are taken where the selector peaks and valued by q
    # (a selector -Q picks the minima: column 0 -> Q(0, 0) = 1, row 0 -> Q(0, 2) = 0, joint -> 0)
    sel = jnp.broadcast_to(jnp.asarray(-Q_NEXT), (6, 3, 3))
    got = oc.option_critic_target(r[:4], disc[:4], q[:4], beta[:4], w[:4], sel[:4])
    np.testing.assert_allclose(got, [1 + g * 1, 1 + g * 1, 1 + g * 0, 1 + g * 0], rtol=1e-6)


def test_critic_target_through_the_learner_all_four_cases():
    """The learner's U: each agent's own beta for its own option, on the right axis of Q."""
    env, learner, state = make(3, cfg=dataclasses.replace(SMALL, gamma=0.9))
    # agent 1: option 0 always ends, 1 never, 2 half; agent 2: option 0 never, 1 always, 2 half
    logit = 30.0
    bias = jnp.array([[logit, -logit, 0.0], [-logit, logit, 0.0]])
    actor = jax.tree.map(lambda x: x, state.actor)
    term = actor["params"]["termination"]
    actor["params"]["termination"] = {"kernel": jnp.zeros_like(term["kernel"]), "bias": bias}
    target_params = set_output(state.critic.target_params, Q_NEXT.ravel())
    obs, _ = env.reset(None)
    options = jnp.array([[1, 0], [0, 0], [1, 1], [0, 1], [0, 1]])
    n = len(options)
    batch = {"action": learner.joint(options), "reward": jnp.array([1.0] * 4 + [3.0]),
             "terminal": jnp.array([False] * 4 + [True]), "next_obs": jnp.broadcast_to(obs, (n, obs.shape[0]))}
    q_t = learner.critic.q_values(target_params, batch["next_obs"])
    y = learner.critic_target(actor)(batch, q_t, q_t)
    want = [1 + 0.9 * 6,   # (1, 0) neither ends: Q(1, 0)
            1 + 0.9 * 8,   # (0, 0) only agent 1: max over column 0
            1 + 0.9 * 7,   # (1, 1) only agent 2: max over row 1
            1 + 0.9 * 9,   # (0, 1) both: joint max
            3.0]           # terminal: no bootstrap
    np.testing.assert_allclose(y, want, rtol=1e-5)


# -- the actor losses -----------------------------------------------------------------------------------
@pytest.mark.parametrize("termination_at", ["next", "current"])
@pytest.mark.parametrize("baseline", ["max", "mean"])
def test_termination_gradient_sign(termination_at, baseline):
    """d loss / d termination logit of the option in force has the sign of A + xi: descent lowers beta
    where the option's advantage is positive and raises it where negative; other options untouched."""
    q = np.array([[5.0, 1.0], [3.0, 0.0]])
    env, learner, state = make(2, termination_at=termination_at, value_baseline=baseline, xi=0.01)
    critic = state.critic.replace(params=set_output(state.critic.params, q.ravel()))
    obs, _ = env.reset(None)
    reduce = np.max if baseline == "max" else np.mean
    for w1, w2 in [(0, 0), (1, 0), (1, 1), (0, 1)]:
        batch = {"obs": obs[None], "next_obs": obs[None], "action": learner.joint(jnp.array([[w1, w2]])),
                 "primitive": jnp.array([[0, 3]]), "reward": jnp.zeros(1), "terminal": jnp.zeros(1, bool)}
        grads = jax.grad(learner.actor_loss)(state.actor, critic, batch)["params"]["termination"]["bias"]
        adv = [q[w1, w2] - reduce(q[:, w2]), q[w1, w2] - reduce(q[w1, :])]  # agent 1: column, agent 2: row
        for i, (w_i, a) in enumerate(zip((w1, w2), adv)):
            assert np.sign(grads[i, w_i]) == np.sign(a + 0.01), (w1, w2, i, a, grads)
            assert np.all(np.delete(np.asarray(grads[i]), w_i) == 0)
        if termination_at == "next":  # no termination gradient where s' is terminal
            batch["terminal"] = jnp.ones(1, bool)
            grads = jax.grad(learner.actor_loss)(state.actor, critic, batch)["params"]["termination"]["bias"]
            np.testing.assert_array_equal(grads, 0.0)


def test_termination_and_policy_losses_hand_computed():
    beta = jnp.array([0.2, 0.7])
    g = jax.grad(oc.termination_loss)(beta, jnp.array([1.0, -2.0]), 0.5, jnp.array([1.0, 1.0]))
    np.testing.assert_allclose(g, [1.5 / 2, -1.5 / 2])
    logits = jnp.log(jnp.array([[0.5, 0.25, 0.25]]))
    loss = oc.intra_option_pg_loss(logits, jnp.array([1]), jnp.array([2.0]), 0.1)
    entropy = -(0.5 * np.log(0.5) + 2 * 0.25 * np.log(0.25))
    np.testing.assert_allclose(loss, -np.log(0.25) * 2.0 - 0.1 * entropy, rtol=1e-6)
    # a positive advantage raises the taken action's probability
    grad = jax.grad(lambda l: oc.intra_option_pg_loss(l, jnp.array([1]), jnp.array([2.0]), 0.0))(logits)
    assert grad[0, 1] < 0 and grad[0, 0] > 0


# -- options ----------------------------------------------------------------------------------------------
def test_choose_options_follows_the_critic():
    _, learner, _ = make(3)
    q = jnp.array([[1.0, 4.0, 0.0],
                   [6.0, 2.0, 7.0],
                   [8.0, 5.0, 3.0]])
    w = jnp.array([0, 2])
    choose = lambda t, eps=0.0, ue=(0.5, 0.5), up=(0.0, 0.0): np.asarray(
        learner.choose_options(q, w, jnp.array(t), eps, jnp.array(ue), jnp.array(up))).tolist()
    assert choose([False, False]) == [0, 2]
    assert choose([True, False]) == [1, 2]   # agent 1: argmax over column 2 (agent 2's option fixed)
    assert choose([False, True]) == [0, 1]   # agent 2: argmax over row 0
    assert choose([True, True]) == [2, 0]    # both: the joint argmax
    # three agents: those whose options end re-choose jointly, the other held
    learner3 = oc.make_learner(envs.make("four_rooms"), SMALL, options=2)
    q3 = jnp.arange(8.0).reshape(2, 2, 2).at[0, 1, 1].set(9.0).at[1, 0, 0].set(10.0)
    got = learner3.choose_options(q3, jnp.array([1, 1, 0]), jnp.array([True, False, True]), 0.0,
                                  jnp.full(3, 0.5), jnp.zeros(3))
    assert np.asarray(got).tolist() == [0, 1, 1]  # argmax over q3[:, 1, :]: 9 at (0, 1, 1)
    # exploring: uniform picks, only for the agents whose options ended
    assert choose([True, False], eps=1.0, up=(0.4, 0.1)) == [1, 2]
    assert choose([False, True], eps=1.0, up=(0.4, 0.1)) == [0, 0]
    assert choose([True, True], eps=1.0, up=(0.4, 0.1)) == [1, 0]
    assert choose([False, False], eps=1.0, up=(0.4, 0.1)) == [0, 2]


def test_options_change_only_at_a_termination():
    env, learner, state = make(4)

    def step(c, key):
        obs, env_state, carry = c
        noise = {name: jax.random.uniform(jax.random.fold_in(key, i), shape)
                 for i, (name, shape) in enumerate(sorted(learner.act_noise.items()))}
        _, beta = learner.actor_out(state.actor, obs)
        actions, new = learner.act(state, obs, carry, noise, 0)  # eps = 1: an ended option is re-picked at random
        ended = (noise["terminate"] < beta[jnp.arange(2), jnp.maximum(carry, 0)]) | (carry == oc.NO_OPTION)
        obs, env_state, _, done, _ = env.step(None, env_state, actions)
        obs0, state0 = env.reset(None)
        pick = lambda a, b: jax.tree.map(lambda x, y: jnp.where(done, x, y), a, b)
        c = (pick(obs0, obs), pick(state0, env_state), jnp.where(done, learner.init_carry(), new))
        return c, (carry, new, ended)

    obs, env_state = env.reset(None)
    run = jax.jit(lambda keys: jax.lax.scan(step, (obs, env_state, learner.init_carry()), keys)[1])
    before, after, ended = (np.asarray(x) for x in run(jax.random.split(jax.random.PRNGKey(1), 200)))
    assert np.all(after >= 0) and np.any(before == oc.NO_OPTION)  # episodes start without options
    changed = after != before
    assert not np.any(changed & ~ended)
    started = before != oc.NO_OPTION
    assert (ended & started).sum() > 40 and (changed & started).sum() > 20  # both branches exercised
    # greedy: an option ends only where beta >= the threshold
    params = learner.policy(state)
    obs, _ = env.reset(None)
    for threshold, ends in [(0.0, True), (1.0, False)]:
        lrn = oc.make_learner(env, SMALL, DOCConfig(actor_hidden=(8,), greedy_termination=threshold), options=4)
        q = lrn.q_joint(params["critic"], obs)
        w = jnp.array([3, 3])
        _, new = lrn.greedy_act(params, obs, w)
        both = np.unravel_index(int(jnp.argmax(q)), q.shape)
        assert new.tolist() == (list(both) if ends else [3, 3])


# -- runner and learning -------------------------------------------------------------------------------
def test_runner_learns_to_triage_on_a_tiny_map_and_writes_results(tmp_path):
    """``jaxusar train doc --options 1,2`` on a tiny map: files per K, a summary, the figure; with
    K = 2 every trial's greedy test triages both victims within 160 episodes."""
    from jaxusar.cli import main

    (tmp_path / "tiny.txt").write_text(TINY.strip() + "\n")
    (tmp_path / "tiny.regions.txt").write_text(TINY_REGIONS)
    out = tmp_path / "doc"
    sets = [f"env.map={tmp_path / 'tiny.txt'}", "env.horizon=20", "train.episodes=160", "train.test_every=10",
            "train.chunk_steps=400", "dqn.learning_starts=100", "dqn.eps_decay_steps=1000", "dqn.hidden=[32]",
            "dqn.target_update_every=50", "dqn.gamma=0.9", "dqn.lr=0.001", "dqn.train_every=1",
            "doc.actor_hidden=[32]", "doc.actor_lr=0.001"]
    main(["train", "doc", "--options", "1,2", "--trials", "3", "--out", str(out), "--quiet"]
         + [arg for kv in sets for arg in ("--set", kv)])
    summary = json.loads((out / "metrics.json").read_text())
    assert summary["options"] == [1, 2] and set(summary["per_options"]) == {"1", "2"}
    for k in (1, 2):
        m = json.loads((out / f"K{k}" / "metrics.json").read_text())
        assert m["options"] == k and m["config"]["doc"]["options"] == [1, 2] and m["config"]["algo"] == "doc"
        assert m["optimal_team_steps"] == 2 and len(m["episodes_to_optimal"]) == len(m["episodes_to_solved"]) == 3
        assert (out / f"K{k}" / "curves.csv").exists() and (out / f"K{k}" / "params" / "trial_2.msgpack").exists()
        assert summary["per_options"][str(k)]["episodes_to_optimal"] == m["episodes_to_optimal"]
    assert (out / "fig5_doc.png").stat().st_size > 10_000
    # learning: with 2 options every trial's best greedy test triages both victims, in few steps
    k2 = summary["per_options"]["2"]
    assert k2["best_test_return"] == [200.0] * 3, k2
    assert max(k2["best_test_steps"]) <= 8 and all(e is not None for e in k2["episodes_to_solved"]), k2
    with pytest.raises(SystemExit):  # a finished run is not overwritten without --force
        main(["train", "doc", "--options", "2", "--out", str(out), "--quiet"])
