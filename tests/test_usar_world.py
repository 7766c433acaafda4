"""The USAR world (DESIGN.md, contract part 2) beyond the step rules (tests/test_contract_model.py): bad
maps and settings, what the observations show and hide, drawn placements, part-1 maps left as they were."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxusar import envs
from jaxusar.envs import LayoutError


def regions_for(grid: str) -> str:
    """One hall region over every open cell."""
    return "R all hall\n---\n" + "\n".join("".join("#" if ch in "#X" else "R" for ch in row) for row in grid.splitlines())


def parse(text: str):
    grid = text.split("---\n")[-1]
    return envs.parse_layout(text, regions_for(grid), "bad")


# -- bad input: one line naming the problem, before anything compiles ------------------------------------
@pytest.mark.parametrize("text, message", [
    ("random_victims: 2 1\n---\nA.?\n.?.", "random_victims=(2, 1) draws 3 victims but the map has only 2 '?' cells"),
    ("---\nA.?\n..V", "1 '?' cells but no victims drawn on them"),
    ("A.#V", "victim 0 at (0, 3) cannot be reached by any medic, even with every rubble cleared"),
    ("A.rV", "victim 0 at (0, 3) is behind rubble and the map has no engineer ('E') to clear it"),
    ("A.rV\n####\nE...", "victim 0 at (0, 3) is behind rubble and no engineer can reach the rubble in the way"),
    ("E.V", "victims but no medic ('A') to triage them"),
    ("colour: red\n---\nA.V", "unknown key 'colour'"),
    ("observation: partial\n---\nA.V", "observation='partial': expected one of full, view"),
    ("view_radius: -1\n---\nA.V", "view_radius='-1': expected an integer >= 0"),
    ("triage_steps: 0\n---\nA.V", "triage_steps='0': expected an integer >= 1"),
    ("random_victims: 1\n---\nA.?", "random_victims='1': expected two integers >= 0"),
    ("critical_reward: lots\n---\nA.C", "critical_reward='lots': expected a number"),
    ("triage_steps: 2\ntriage_steps: 3\n---\nA.V", "header key 'triage_steps' is set twice"),
    ("no colon here\n---\nA.V", "header line 'no colon here' is not 'key: value'"),
])
def test_bad_maps_are_one_line_errors_naming_the_problem(text, message):
    with pytest.raises(LayoutError, match=re.escape(message)) as info:
        parse(text)
    assert "\n" not in str(info.value) and "layout 'bad'" in str(info.value)


def test_an_engineer_behind_rubble_clears_its_way_in_waves():
    layout = parse("Er.r.\n####.\nA...V")  # the engineer clears (0, 1), walks on, clears (0, 3)
    assert layout.rubble.sum() == 2
    parse("A..r\n...E\n..rV")  # the victim's only other side is under rubble the engineer reaches


@pytest.mark.parametrize("overrides, message", [
    ({"observation": "foo"}, "override: observation='foo': expected one of full, view"),
    ({"random_victims": (7, 2)}, "draws 9 victims but the map has only 2 '?' cells"),
    ({"random_victims": (0, 0)}, "2 '?' cells but no victims drawn on them"),
    ({"critical_expires": 0}, "critical_expires=0: expected an integer >= 1"),
])
def test_bad_overrides_are_errors_before_anything_compiles(overrides, message):
    layout = parse("random_victims: 1 0\n---\nA.?\n..?")
    with pytest.raises(LayoutError, match=re.escape(message)):
        envs.make(layout, **overrides)


def test_unknown_override_names_the_allowed_ones():
    with pytest.raises(TypeError, match=r"unknown env override\(s\) \['colour'\]; allowed: .*'view_radius'"):
        envs.make("two_rooms", colour="red")


def test_header_sets_defaults_and_an_override_wins():
    layout = parse("triage_steps: 3\nview_radius: none\nobservation: view\n---\nA.V")
    env = envs.make(layout)
    assert (env.triage_steps, env.view_radius, env.observation) == (3, None, "view")
    env = envs.make(layout, triage_steps=1, view_radius=2, observation="full")
    assert (env.triage_steps, env.view_radius, env.observation) == (1, 2, "full")
    assert env.obs_shape == (env.obs_dim,) and envs.make(layout).obs_shape == (1, envs.make(layout).obs_dim)


# -- part-1 maps keep every number ---------------------------------------------------------------------
@pytest.mark.parametrize("name", ["two_rooms", "three_rooms", "four_rooms", "office"])
def test_part1_maps_keep_part1s_observation_and_reset(name):
    env = envs.make(name)
    assert env.part1 and env.n_drawn == 0 and not np.any(env.roles) and not np.any(env.victim_kind)
    assert env.obs_dim == env.n_agents * (env.height + env.width + 4) + env.n_victims
    obs, state = env.reset(jax.random.PRNGKey(0))
    expected = []
    for (r, c) in env.layout.agent_start:
        expected += [np.eye(env.height)[r], np.eye(env.width)[c], np.eye(4)[env.start_dir]]
    np.testing.assert_array_equal(obs, np.concatenate(expected + [np.zeros(env.n_victims)]))
    _, other = env.reset(jax.random.PRNGKey(1))  # nothing is drawn: the key changes nothing
    jax.tree.map(np.testing.assert_array_equal, state, other)


def test_part1_state_with_four_fields_still_steps():
    env = envs.make("two_rooms")
    start = env.initial_state()
    four = envs.EnvState(agent_pos=start.agent_pos, agent_dir=start.agent_dir, triaged=start.triaged, t=start.t)
    a = env.step(None, four, jnp.array([0, 0]))
    b = env.step(None, start, jnp.array([0, 0]))
    jax.tree.map(np.testing.assert_array_equal, a[:4], b[:4])


# -- drawn placements --------------------------------------------------------------------------------------
def test_vmapped_resets_draw_different_worlds():
    env = envs.make("minimap")
    _, states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 64))
    placements = {np.asarray(p).tobytes() for p in states.victim_pos}
    assert len(placements) == 64
    cells = {tuple(c) for c in env.layout.random_cells}
    for pos in np.asarray(states.victim_pos):
        assert len({tuple(p) for p in pos}) == env.n_victims and all(tuple(p) in cells for p in pos)


def test_a_map_that_draws_victims_needs_a_key():
    with pytest.raises(ValueError, match="draws victims at reset: pass a PRNG key"):
        envs.make("minimap").initial_state()


# -- observations --------------------------------------------------------------------------------------
def rollout(env, key, steps: int):
    """(observations, states) of a rollout under random actions biased to FORWARD and the tool, resetting
    at done; numpy."""
    step = jax.jit(env.step)
    obs, state = env.reset(key)
    out = []
    rng = np.random.default_rng(int(jax.random.randint(key, (), 0, 2 ** 30)))
    for _ in range(steps):
        out.append((np.asarray(obs), jax.tree.map(np.asarray, state)))
        actions = rng.choice(4, env.n_agents, p=[0.5, 0.15, 0.15, 0.2]).astype(np.int32)
        obs, state, _, done, _ = step(None, state, jnp.asarray(actions))
        if bool(done):
            key = jax.random.fold_in(key, len(out))
            obs, state = env.reset(key)
    return out


@pytest.mark.parametrize("name, overrides", [
    ("two_rooms_rubble", {}), ("minimap", {"observation": "full"}),
    ("minimap", {"observation": "full", "critical_expires": None, "horizon": 40}),
])
def test_full_observation_determines_the_state(name, overrides):
    """Two states with one observation are one state, over many visited states of several draws."""
    env = envs.make(name, **overrides)
    by_obs = {}
    for k in range(3):
        for obs, state in rollout(env, jax.random.PRNGKey(k), 150):
            fields = jax.tree.leaves(state)
            seen = by_obs.setdefault(obs.tobytes(), fields)
            for a, b in zip(seen, fields):
                np.testing.assert_array_equal(a, b)
    assert len(by_obs) > 100


def test_full_observation_tells_rubble_progress_death_and_time_apart():
    env = envs.make("minimap", observation="full")
    _, state = env.reset(jax.random.PRNGKey(0))
    base = np.asarray(env.observe(state))
    changes = {
        "rubble": state.rubble.at[4, 11].set(False),
        "progress": state.progress.at[6].set(1),
        "dead": state.dead.at[7].set(True),
        "t": state.t + 1,
        "seen": state.seen.at[0, 0].set(True),
        "victim_pos": state.victim_pos.at[0].set(jnp.asarray(
            [c for c in env.layout.random_cells if not (np.asarray(state.victim_pos) == c).all(-1).any()][0])),
    }
    for field, value in changes.items():
        assert not np.array_equal(base, env.observe(state.replace(**{field: value}))), field


def test_view_hides_unseen_victims_on_the_minimap():
    """Moving an unseen victim to another free unseen '?' cell changes no agent's observation, in visited
    states of several draws; a seen victim does show."""
    env = envs.make("minimap")
    observe = jax.jit(env.observe)
    moved = 0
    for k in range(2):
        for obs, state in rollout(env, jax.random.PRNGKey(k), 60)[::6]:
            pos = state.victim_pos
            taken = {tuple(p) for p in pos}
            free = [tuple(c) for c in env.layout.random_cells if tuple(c) not in taken and not state.seen[tuple(c)]]
            for v in range(env.n_victims):
                if state.seen[tuple(pos[v])] or not free:
                    continue
                other = jax.tree.map(jnp.asarray, state).replace(victim_pos=jnp.asarray(pos).at[v].set(jnp.asarray(free[0])))
                np.testing.assert_array_equal(obs, observe(other))
                moved += 1
    assert moved > 20
    _, state = env.reset(jax.random.PRNGKey(0))
    shown = state.replace(seen=jnp.ones_like(state.seen))
    assert not np.array_equal(observe(shown), observe(shown.replace(victim_pos=state.victim_pos[::-1])))


def test_view_rows_are_each_agents_own():
    env = envs.make("minimap")
    obs, _ = env.reset(jax.random.PRNGKey(0))
    assert obs.shape == (env.n_agents, env.obs_dim) == (3, sum(env.obs_blocks))
    h, w = env.height, env.width
    for i, (r, c) in enumerate(env.layout.agent_start):
        np.testing.assert_array_equal(obs[i, :h], np.eye(h)[r])
        np.testing.assert_array_equal(obs[i, h:h + w], np.eye(w)[c])
        assert obs[i, h + w + 4] == (env.roles[i] == envs.ENGINEER)


def test_view_window_turns_with_the_agent():
    """The window's top row lies ahead: facing a wall puts wall classes there, whichever way the wall is."""
    from jaxusar.envs.observations import CELL_CLASSES, WALL

    layout = envs.parse_layout("#####\n#...#\n#.A.#\n#...#\n#.V.#\n#####",
                               "R all hall\n---\n#####\n#RRR#\n#RRR#\n#RRR#\n#RRR#\n#####", "box")
    env = envs.make(layout, observation="view", view_radius=2)
    h, w, k = env.height, env.width, 2
    start = h + w + 4 + 1
    n = len(CELL_CLASSES)
    for d, ahead_is_wall in ((envs.NORTH, True), (envs.SOUTH, False), (envs.WEST, True), (envs.EAST, True)):
        state = env.initial_state().replace(agent_dir=jnp.asarray([d], jnp.int32))
        window = np.asarray(env.observe(state))[0, start:start + (2 * k + 1) ** 2 * n].reshape(2 * k + 1, 2 * k + 1, n)
        top = window[0].argmax(-1)  # two cells ahead
        assert (top == WALL).all() == ahead_is_wall, (d, top)


def test_draws_are_uniform_over_ordered_subsets():
    """Every ordered choice of 3 of 5 cells comes up about equally often (60 of them, 1,000 expected each:
    a sort-free sampler that favoured low indices or repeated one would be off by far more than 15%)."""
    from jaxusar.envs.usar import draw_without_replacement

    draws = np.asarray(jax.jit(jax.vmap(lambda k: draw_without_replacement(k, 5, 3)))(
        jax.random.split(jax.random.PRNGKey(0), 60_000)))
    assert all(len(set(row)) == 3 for row in draws)
    _, counts = np.unique(draws, axis=0, return_counts=True)
    assert len(counts) == 60 and counts.min() > 850 and counts.max() < 1150


# -- encodings ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["two_rooms", "four_rooms", "office", "two_rooms_rubble", "minimap"])
@pytest.mark.parametrize("observation", ["full", "view"])
def test_codes_are_the_one_hot_observation_block_by_block(name, observation):
    """encoding="codes" gives one integer per one-hot block, and the codec maps it to and from the one-hot
    observation exactly, on visited states (a block listed in another order than it is written, or a flag
    coded unlike the codec's convention, breaks the round trip)."""
    one_hot = envs.make(name, observation=observation)
    codes_env = envs.make(name, observation=observation, encoding="codes")
    codec = one_hot.obs_codec
    rows = one_hot.obs_shape[:-1]
    assert codes_env.obs_shape == (*rows, len(one_hot.obs_blocks)) and codes_env.obs_dtype == codec.dtype
    observe = jax.jit(codes_env.observe)
    for obs, state in rollout(one_hot, jax.random.PRNGKey(1), 60):
        codes = observe(state)
        assert codes.shape == codes_env.obs_shape and codes.dtype == codec.dtype
        np.testing.assert_array_equal(np.asarray(codec.decode(codes)), obs)
        np.testing.assert_array_equal(np.asarray(codec.encode(obs)), np.asarray(codes))


def test_a_bad_encoding_is_a_one_line_error():
    with pytest.raises(ValueError, match=r"^override encoding='bits': expected one of one_hot, codes$"):
        envs.make("two_rooms", encoding="bits")
