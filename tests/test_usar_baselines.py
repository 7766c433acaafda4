"""The baselines (IQL, option-critic) on the USAR world's maps (contract part 2), in both observations.

Budgets are tiny (one trial, a handful of 12-step episodes, 8-wide nets, one chunk): these check that
the learners run and learn on every map and observation, not how well. Most of the time is XLA
compiling each map's chunk once.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxusar import algos, config, envs, planning
from jaxusar.algos import iql, option_critic
from jaxusar.config import ConfigError, DOCConfig, DQNConfig
from jaxusar.experiments import train

TINY = ["env.horizon=12", "train.episodes=4", "train.test_every=2", "train.chunk_steps=48", "dqn.hidden=[8]",
        "dqn.batch_size=4", "dqn.buffer_capacity=64", "dqn.learning_starts=0", "dqn.train_every=4"]
TINY_DOC = ["doc.options=[2]", "doc.actor_hidden=[8]"]


@pytest.fixture(autouse=True, scope="module")
def cheap_compiles():
    """XLA's least optimising compiles for this file (a third less compile time; nothing here is timed or
    compared with another file's numbers), then the setting as it was."""
    before = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", True)
    yield
    jax.config.update("jax_disable_most_optimizations", before)


@pytest.fixture
def any_reference(monkeypatch):
    """What "optimal" means is planning's (the experiments call ``planning.team_reference``, tested in
    test_planning.py); these tests are about the learners, so they skip its searches and compiles."""
    monkeypatch.setattr(planning, "team_reference",
                        lambda env, *args, **kw: {"steps": env.horizon, "reference": "stub", "lower_bound": 1})


def transition(env, obs, state, actions):
    next_obs, _, reward, done, info = jax.jit(env.step)(None, state, jnp.asarray(actions, jnp.int32))
    return {"obs": obs, "action": jnp.asarray(actions, jnp.int32), "reward": reward, "next_obs": next_obs,
            "done": done, "info": info, "carry": jnp.zeros(env.n_agents, jnp.int32),
            "next_carry": jnp.zeros(env.n_agents, jnp.int32)}


@pytest.mark.parametrize("observation", ["full", "view"])
@pytest.mark.parametrize("map_name", ["two_rooms_rubble", "minimap"])
@pytest.mark.parametrize("algo", ["iql", "doc"])
def test_baselines_train_on_the_usar_maps(algo, map_name, observation, any_reference):
    sets = [f"env.map={map_name}", f"env.observation={observation}", *TINY] + (TINY_DOC if algo == "doc" else [])
    cfg = config.load(sets=sets, defaults=algos.defaults(algo))
    keys = train.trial_keys(cfg.seed, 1)
    exp = train.experiment(cfg, keys)
    env = exp.env
    assert env.observation == observation and env.n_agents == 3
    assert env.obs_shape == ((3, env.obs_dim) if observation == "view" else (env.obs_dim,))
    (stage,) = [s for chain in exp.chains for s in chain]
    state = stage.trainer.train(stage.keys)
    r = stage.trainer.results(state)
    np.testing.assert_array_equal(r["train_length"], [[12] * 4])  # nobody triages everything in 12 steps
    assert r["test_length"].shape == (1, 2) and (r["test_length"] > 0).all()
    learner = state.trials.learner
    updates = learner.updates if algo == "iql" else learner.critic.updates
    assert (np.asarray(updates) == 12).all()  # 48 env steps, a learning step every 4
    assert np.isfinite(r["train_return"]).all()


def test_iql_feeds_each_agent_its_own_row():
    """With per-agent observations learner i's network sees obs[i] and its replay stores obs[i]; feeding
    every learner row 0 (or the whole stack) would fail here."""
    env = envs.make("two_rooms_rubble", observation="view")
    obs, state = jax.jit(env.reset)(None)
    assert obs.shape == (3, env.obs_dim) and not np.array_equal(obs[0], obs[1])
    learner = iql.make_learner(env, DQNConfig(hidden=(8,), batch_size=4, buffer_capacity=8))
    tr = transition(env, obs, state, [0, 1, 3])

    @jax.jit  # one program, not an XLA compile per eager op
    def run(tr):
        st = learner.init(jax.random.PRNGKey(0), tr)
        own = [learner.dqn.q_values(jax.tree.map(lambda x: x[i], st.params), tr["obs"][i]) for i in range(3)]
        first = [learner.dqn.q_values(jax.tree.map(lambda x: x[i], st.params), tr["obs"][0]) for i in range(3)]
        st = learner.observe(st, tr)
        stored = {k: learner.dqn.decode(st.replay.rows[k][:, 0]) for k in ("obs", "next_obs")}
        return (learner._q(st.params, tr["obs"]), jnp.stack(own), jnp.stack(first),
                learner.greedy_act(st.params, tr["obs"], None)[0], stored, st.replay.rows["action"][:, 0])

    q, own, first, greedy, stored, action = run(tr)
    np.testing.assert_array_equal(q, own)
    assert not np.allclose(q[1:], first[1:])
    np.testing.assert_array_equal(greedy, np.argmax(own, -1))
    np.testing.assert_array_equal(stored["obs"], obs)  # [learner, obs_dim]: each its own row
    np.testing.assert_array_equal(stored["next_obs"], tr["next_obs"])
    np.testing.assert_array_equal(action, [0, 1, 3])


def test_option_critic_actors_see_their_own_rows_and_the_critic_all_of_them():
    env = envs.make("two_rooms_rubble", observation="view")
    obs, state = jax.jit(env.reset)(None)
    oc = option_critic.make_learner(env, DQNConfig(hidden=(8,), batch_size=4, buffer_capacity=8),
                                    DOCConfig(options=(2,), actor_hidden=(8,)))
    tr = transition(env, obs, state, [0, 1, 3])
    tr["next_carry"] = jnp.array([1, 0, 1], jnp.int32)

    @jax.jit
    def run(tr):
        st = oc.init(jax.random.PRNGKey(0), tr)
        joint = oc.joint_obs(tr["obs"])
        actor = lambda i, x: oc.actor_net.apply(jax.tree.map(lambda p: p[i], st.actor), x)[0]
        own = jnp.stack([actor(i, tr["obs"][i]) for i in range(3)])
        first = jnp.stack([actor(i, tr["obs"][0]) for i in range(3)])
        q = oc.q_joint(st.critic.params, joint).ravel(), oc.critic.q_values(st.critic.params, joint)
        st = oc.observe(st, tr)
        return joint, oc.actor_out(st.actor, joint)[0], own, first, q, oc.critic.decode(st.critic.replay.rows["obs"][0])

    joint, logits, own, first, (q_joint, q_flat), stored = run(tr)
    assert joint.shape == (3 * env.obs_dim,)
    np.testing.assert_allclose(logits, own, rtol=1e-6)  # actor i on obs[i]
    assert not np.allclose(logits[1:], first[1:])
    np.testing.assert_array_equal(q_joint, q_flat)  # the critic on the rows side by side
    np.testing.assert_array_equal(stored, joint)


def test_hierarchical_runs_under_view_and_says_in_one_line_when_it_cannot_run_as_configured():
    """Every rule of the contract, "view" included, is the method's; what it refuses is a setting: here a
    flat coordinator over 18 options ^ 3 agents, before anything compiles."""
    cfg = config.load(sets=["env.map=minimap"], defaults=algos.defaults("hierarchical"))
    assert cfg.env.observation is None and train.unsupported("hierarchical", cfg) is None  # the map's: view
    flat = config.load(sets=["env.map=minimap", "hierarchical.coordinator.kind=flat",
                             "hierarchical.coordinator.max_joint_options=1000"],
                       defaults=algos.defaults("hierarchical"))
    why = train.unsupported("hierarchical", flat)
    assert why.startswith("the flat coordinator on 'minimap' would choose among 3,375 joint options (15 options ^ 3 "
                          "agents), more than hierarchical.coordinator.max_joint_options=1,000") and "\n" not in why
    with pytest.raises(ConfigError, match=re.escape(why)):
        train.experiment(flat, train.trial_keys(0, 1))


def test_env_overrides_are_checked_by_the_config_and_reach_the_env():
    with pytest.raises(ConfigError, match=r"env.observation='foo' is out of range \(full .* or view"):
        config.load(sets=["env.observation=foo"])
    for bad in ("env.view_radius=-1", "env.triage_steps=0", "env.critical_expires=soon", "env.random_victims=[1]"):
        with pytest.raises(ConfigError, match=bad.split("=")[0]):
            config.load(sets=[bad])
    cfg = config.load(sets=["env.map=minimap", "env.observation=full", "env.critical_expires=none",
                            "env.random_victims=[2, 1]"])
    env = envs.make(cfg.env.map, **cfg.env.overrides())
    assert env.observation == "full" and env.critical_expires is None and env.n_drawn == 3
    assert env.view_radius == 2  # left to the map's header
    # settings left to the map are not in the config's dict: configs that set none hash as before
    assert set(config.load().to_dict()["env"]) == {"map", "horizon", "triage_reward", "step_penalty", "start_dir"}
    assert cfg.to_dict()["env"]["observation"] == "full"
