"""The JaxMARL and PettingZoo adapters (jaxusar.interop).

The JaxMARL adapter's dict API is tested without jaxmarl (only its spaces need it); PettingZoo's own
``parallel_api_test`` checks the Parallel adapter where pettingzoo is installed (the ``test`` extra has it).
"""

import subprocess
import sys
import textwrap
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxusar import envs
from jaxusar.envs import TRIAGE, TURN_LEFT, WEST
from jaxusar.interop import JaxMARLEnv, ParallelEnv

# A joint plan on two_rooms that triages both victims: medic 1 the bottom one at step 19, medic 0 the
# top one at step 24 (F forward, L/R turn, T triage; from the starts, both facing NORTH).
PLAN = {"agent_0": "LLFFFRFFFFFFFFFFFFFFRFFT", "agent_1": "FFRFFFFFFFFFFFFRFLTLLLLL"}
CODE = {"F": 0, "L": 1, "R": 2, "T": 3}


def same_tree(a, b) -> bool:
    return jax.tree.structure(a) == jax.tree.structure(b) and all(
        np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


# -- JaxMARL ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def two_rooms():
    return JaxMARLEnv(envs.make("two_rooms", horizon=5))


def test_jaxmarl_names_roles_and_avail_actions(two_rooms):
    assert two_rooms.agents == ["agent_0", "agent_1"] and two_rooms.num_agents == 2
    assert two_rooms.agent_classes == {"medic": ["agent_0", "agent_1"]}
    assert two_rooms.name == "jaxusar_two_rooms" and two_rooms.max_steps == 5
    rubble = JaxMARLEnv("two_rooms_rubble")
    assert rubble.agents == ["agent_0", "agent_1", "agent_2"]
    assert rubble.agent_classes == {"medic": ["agent_0", "agent_1"], "engineer": ["agent_2"]}
    _, state = two_rooms.reset(jax.random.PRNGKey(0))
    avail = two_rooms.get_avail_actions(state)
    assert set(avail) == set(two_rooms.agents)
    for mask in avail.values():
        assert mask.shape == (4,) and mask.dtype == jnp.bool_ and bool(mask.all())
    with pytest.raises(KeyError, match="agent_1"):
        two_rooms.step_env(jax.random.PRNGKey(0), state, {"agent_0": 0})
    with pytest.raises(TypeError, match="USAREnv"):
        JaxMARLEnv(object())


def test_jaxmarl_step_and_auto_reset_keep_the_final_step(two_rooms):
    env = two_rooms.env
    obs0, state0 = two_rooms.reset(jax.random.PRNGKey(0))
    assert set(obs0) == set(two_rooms.agents)
    want_obs, want_state = env.reset(None)
    assert same_tree(state0, want_state)
    for o in obs0.values():  # "full": the shared vector for every agent
        assert o.shape == (env.obs_dim,) and o.dtype == jnp.float32
        np.testing.assert_array_equal(o, want_obs)

    # a step that does not end the episode: the env's own step, spread over the agents
    actions = {"agent_0": jnp.int32(TURN_LEFT), "agent_1": jnp.int32(0)}
    obs, state, rewards, dones, infos = two_rooms.step(jax.random.PRNGKey(1), state0, actions)
    want_obs, want_state, *_ = jax.jit(env.step)(None, state0, jnp.array([TURN_LEFT, 0], jnp.int32))
    assert same_tree(state, want_state) and int(state.t) == 1
    for a in two_rooms.agents:
        np.testing.assert_array_equal(obs[a], want_obs)
        assert rewards[a].dtype == jnp.float32 and float(rewards[a]) == 0.0
    assert set(dones) == {*two_rooms.agents, "__all__"} and not any(bool(d) for d in dones.values())
    assert set(infos) == {"newly_triaged", "terminated", "truncated"}

    # the last step of the horizon triages a victim: reward and dones are the final step's, the
    # observation and state are the reset's
    last = state0.replace(agent_pos=state0.agent_pos.at[0].set(jnp.array([0, 1])),
                          agent_dir=state0.agent_dir.at[0].set(WEST), t=jnp.int32(env.horizon - 1))
    obs, state, rewards, dones, infos = two_rooms.step(
        jax.random.PRNGKey(2), last, {"agent_0": TRIAGE, "agent_1": TURN_LEFT})
    assert all(bool(d) for d in dones.values())
    assert [float(rewards[a]) for a in two_rooms.agents] == [100.0, 100.0]
    assert bool(infos["newly_triaged"][0]) and bool(infos["truncated"])
    assert same_tree(state, state0)
    for a in two_rooms.agents:
        np.testing.assert_array_equal(obs[a], obs0[a])


def test_jaxmarl_view_rows_drawn_victims_under_vmap():
    adapter = JaxMARLEnv(envs.make("minimap", horizon=2))  # observation: view; victims drawn at reset
    env = adapter.env
    reset, step = jax.jit(jax.vmap(adapter.reset)), jax.jit(jax.vmap(adapter.step))
    keys = jax.random.split(jax.random.PRNGKey(3), 4)
    obs, state = reset(keys)
    views, want_state = jax.jit(jax.vmap(env.reset))(keys)  # [batch, n_agents, obs_dim]
    assert views.shape == (4, env.n_agents, env.obs_dim) and same_tree(state, want_state)
    for i, a in enumerate(adapter.agents):
        np.testing.assert_array_equal(obs[a], views[:, i])
    assert len({tuple(np.asarray(p).ravel()) for p in state.victim_pos}) > 1  # the keys draw different victims

    actions = {a: jnp.zeros(4, jnp.int32) for a in adapter.agents}
    step_keys = jax.random.split(jax.random.PRNGKey(4), 4)
    obs, state, _, dones, _ = step(step_keys, state, actions)
    assert not bool(dones["__all__"].any()) and bool((state.t == 1).all())
    obs, state, rewards, dones, _ = step(step_keys, state, actions)  # horizon: every episode resets
    assert bool(dones["__all__"].all()) and bool((state.t == 0).all())
    assert rewards["agent_0"].shape == (4,)
    # the reset is JaxMARL's: from the second half of the step key's split
    want_obs, want_state = reset(jax.vmap(lambda k: jax.random.split(k)[1])(step_keys))
    assert same_tree(state, want_state) and same_tree(obs, want_obs)


def test_jaxmarl_spaces(two_rooms):
    pytest.importorskip("jaxmarl")
    for adapter in (two_rooms, JaxMARLEnv("minimap")):
        for a in adapter.agents:
            obs_space, act_space = adapter.observation_space(a), adapter.action_space(a)
            assert obs_space is adapter.observation_space(a) and act_space is adapter.action_space(a)
            assert obs_space.shape == (adapter.env.obs_dim,) and obs_space.dtype == jnp.float32
            assert (obs_space.low, obs_space.high) == (0.0, 1.0)
            assert act_space.n == 4 and act_space.shape == ()
        assert set(adapter.observation_spaces) == set(adapter.agents)


def test_neither_library_is_needed_to_import():
    """Without jaxmarl, pettingzoo and gymnasium: the module imports, the JaxMARL dict API builds,
    and using what needs a library says which extra to install."""
    code = textwrap.dedent("""
        import sys
        for name in ("jaxmarl", "pettingzoo", "gymnasium"):
            sys.modules[name] = None  # any import of them now fails
        import jaxusar.interop as interop
        env = interop.JaxMARLEnv("two_rooms")
        assert env.agents == ["agent_0", "agent_1"]
        for use in (lambda: env.observation_space("agent_0"), lambda: interop.ParallelEnv("two_rooms")):
            try:
                use()
            except ImportError as e:
                assert "pip install 'jaxusar[bench]'" in str(e), e
                print(e)
            else:
                raise AssertionError("no ImportError")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "JaxMARLEnv's spaces needs jaxmarl" in out.stdout and "ParallelEnv needs pettingzoo" in out.stdout


# -- PettingZoo ------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["two_rooms", "two_rooms_rubble", "minimap"])
def test_parallel_api_test(name):
    test = pytest.importorskip("pettingzoo.test")
    env = ParallelEnv(envs.make(name, horizon=25), seed=1)  # horizon < num_cycles: episodes end
    assert env.observation_space("agent_0").shape == (env.env.obs_dim,)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # parallel_api_test warns on what it does not assert
        test.parallel_api_test(env, num_cycles=100)
    assert env.agents == [] and env.metadata["name"] == f"jaxusar_{name}"


def test_parallel_terminates_truncates_renders_and_rejects_bad_input():
    pettingzoo = pytest.importorskip("pettingzoo")
    env = ParallelEnv("two_rooms", render_mode="ansi")
    assert isinstance(env, pettingzoo.ParallelEnv) and isinstance(env, ParallelEnv)
    assert env.possible_agents == ["agent_0", "agent_1"] and env.agents == []
    with pytest.raises(RuntimeError, match="reset"):
        env.step({"agent_0": 0, "agent_1": 0})
    obs, infos = env.reset(seed=0)
    assert env.agents == env.possible_agents and set(infos) == set(env.agents)
    assert obs["agent_0"].dtype == np.float32 and env.observation_space("agent_0").contains(obs["agent_0"])
    assert "t=0" in env.render()
    with pytest.raises(KeyError, match="agent_1"):
        env.step({"agent_0": 0})
    with pytest.raises(ValueError, match="0..3"):
        env.step({"agent_0": 0, "agent_1": 7})
    total, steps = 0.0, 0
    for step in zip(*PLAN.values()):
        obs, rewards, terms, truncs, infos = env.step({a: CODE[c] for a, c in zip(PLAN, step)})
        total, steps = total + rewards["agent_0"], steps + 1
        assert isinstance(rewards["agent_0"], float) and not any(truncs.values())
    assert all(terms.values()) and env.agents == [] and total == 200.0 and steps == 24
    assert infos["agent_0"]["newly_triaged"].tolist() == [True, False]
    env.close()
    with pytest.raises(ValueError, match="render_mode"):
        ParallelEnv("two_rooms", render_mode="rgb_array")

    env = ParallelEnv(envs.make("two_rooms", horizon=3))
    env.reset()
    for _ in range(3):
        _, _, terms, truncs, _ = env.step({"agent_0": TURN_LEFT, "agent_1": TURN_LEFT})
    assert all(truncs.values()) and not any(terms.values()) and env.agents == []


def test_parallel_seeds_draw_victims_and_repeat():
    pytest.importorskip("pettingzoo")
    env = ParallelEnv("minimap", seed=0)
    draws = []
    for seed in (5, 5, 6, None):
        env.reset(seed=seed)
        draws.append(np.asarray(env.env_state.victim_pos))
    assert np.array_equal(draws[0], draws[1]) and not np.array_equal(draws[1], draws[2])
    assert not np.array_equal(draws[2], draws[3])  # no seed: the key stream goes on
    # the same seed gives the same episode, step for step (PettingZoo's own seed test)
    from pettingzoo.test import parallel_seed_test

    parallel_seed_test(lambda: ParallelEnv(envs.make("two_rooms_rubble", horizon=25)), num_cycles=50)
