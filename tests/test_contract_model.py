"""The env against an independent model of DESIGN.md's contract, parts 1 and 2 (tests/usar_model.py).

1. Random rollouts on small hand-written maps and on every shipped map: the model's state, reward and done
   equal the env's at every step, every field.
2. Victims drawn at reset: distinct '?' cells, different across keys, every '?' cell drawn; and the view
   observation does not show where an unseen victim is.
3. Targeted rules that classic bugs break, each run on the model and on the env with the same expectations
   worked out by hand (so the model's own tests are the `[model]` cases).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from usar_model import CRITICAL, EAST, FORWARD, NORTH, REGULAR, SOUTH, TOOL, TURN_LEFT, TURN_RIGHT, WEST, Model, State

from jaxusar import envs

F, L, R, T = FORWARD, TURN_LEFT, TURN_RIGHT, TOOL
N_SEEDS = 4


# -- hand-written maps -----------------------------------------------------------------------------
# Two rooms joined by a rubble-filled doorway (a region of its own), an engineer facing it (start_dir EAST
# below) and three medics, a critical victim that needs two TRIAGE actions.
DOORWAY = """\
; rubble in the doorway between two rooms
critical_triage_steps: 2
critical_expires: 40
view_radius: 1
---
A..V#.V.
....#...
...Er..C
....#...
A...#.AV
"""
DOORWAY_REGIONS = """\
L left room
D door hall
R right room
---
LLLL#RRR
LLLL#RRR
LLLLDRRR
LLLL#RRR
LLLL#RRR
"""

# Victims drawn among five '?' cells: two regular, one critical, after the fixed one.
DRAWN = """\
random_victims: 2 1
view_radius: 2
critical_expires: 12
observation: view
---
?..#..?
.A.#.E.
...r...
##.#.##
?.....?
...V.A?
"""
DRAWN_REGIONS = """\
T top_left room
U top_right room
H hall hall
---
TTT#UUU
TTT#UUU
TTTUUUU
##H#H##
HHHHHHH
HHHHHHH
"""

# Four medics in a cramped map of four regions, seeing only their own cell.
CROWDED = """\
triage_steps: 2
critical_triage_steps: 3
view_radius: 0
---
V..#...
.AA.AA.
#.##.#C
V..#..V
"""
CROWDED_REGIONS = """\
a north_west room
b north_east room
c south_west room
d south_east room
---
aaa#bbb
aaaabbb
#c##d#d
ccc#ddd
"""

# Rubble everywhere, two engineers, critical victims that expire at t = 5; overridden below.
RUBBLE = """\
critical_expires: 5
critical_reward: 500
---
Er..C
rA..V
.r.r.
E.r.C
"""
RUBBLE_REGIONS = """\
a west hall
b east room
---
aabbb
aabbb
aabbb
aabbb
"""


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    layout: str  # layout text (a shipped map's file)
    regions: str | None = None  # region text; None: a shipped map, whose region grid the env has
    overrides: tuple = ()  # envs.make overrides, as (key, value) pairs
    expect: frozenset = frozenset()  # events the rollouts must produce, so that the comparison is not vacuous

    def __str__(self):
        return self.name + "".join(f"-{k}={v}" for k, v in self.overrides)


def shipped_layout_text(name: str) -> str:
    return (pathlib.Path(envs.__file__).parent / "layouts" / f"{name}.txt").read_text()


DRAWN_CASE = Case("drawn", DRAWN, DRAWN_REGIONS, expect=frozenset({"triage"}))  # the rest depends on the env's draw
CASES = [
    Case("doorway", DOORWAY, DOORWAY_REGIONS, (("start_dir", EAST),), expect=frozenset({"clear", "triage"})),
    DRAWN_CASE,
    Case("crowded", CROWDED, CROWDED_REGIONS, expect=frozenset({"triage", "progress"})),
    Case(
        "rubble",
        RUBBLE,
        RUBBLE_REGIONS,
        overrides=(("horizon", 30), ("step_penalty", -1.0), ("triage_reward", 10.0), ("start_dir", EAST), ("critical_reward", 50.0)),
        expect=frozenset({"clear", "triage", "dead"}),
    ),
    Case("drawn", DRAWN, DRAWN_REGIONS, overrides=(("view_radius", None), ("critical_expires", 30), ("triage_steps", 2), ("random_victims", (1, 2)))),
    *[Case(name, shipped_layout_text(name)) for name in envs.available_layouts()],
    Case("two_rooms", shipped_layout_text("two_rooms"), overrides=(("horizon", 40), ("start_dir", SOUTH), ("view_radius", 2), ("step_penalty", -0.5))),
]


@functools.lru_cache(maxsize=None)
def build(case: Case):
    """(env, model, jitted reset, jitted step): one env and one compilation per case."""
    overrides = dict(case.overrides)
    if case.regions is None:
        env = envs.make(case.name, **overrides)
        model = Model(case.layout, np.asarray(env.graph.cell_region), **overrides)
    else:
        env = envs.make(envs.parse_layout(case.layout, case.regions, case.name), **overrides)
        model = Model.from_texts(case.layout, case.regions, **overrides)
    return env, model, jax.jit(env.reset), jax.jit(env.step)


# -- comparing -------------------------------------------------------------------------------------
def differences(model_state: State, env_state) -> list[str]:
    """One line per field where the env's state differs from the model's."""
    lines = []
    for name in State.FIELDS:
        want, got = np.asarray(getattr(model_state, name)), np.asarray(getattr(env_state, name))
        if want.shape != got.shape:
            lines.append(f"{name}: model shape {want.shape}, env shape {got.shape}")
        elif not np.array_equal(want, got):
            if want.ndim == 2 and want.dtype == bool:  # a grid: name the cells
                lines.append(f"{name}: model only at {np.argwhere(want & ~got).tolist()}, env only at {np.argwhere(got & ~want).tolist()}")
            else:
                lines.append(f"{name}: model {want.tolist()}, env {got.tolist()}")
    return lines


def assert_same(model_state: State, env_state, where: str) -> None:
    lines = differences(model_state, jax.device_get(env_state))
    assert not lines, f"{where}:\n  " + "\n  ".join(lines)


def biased_action(rng: np.random.Generator, model: Model, state: State, agent: int) -> int:
    """Mostly the tool where it acts, otherwise mostly forward: so that triage, clearing and collisions happen."""
    if model.tool_target(state, agent) is not None and rng.random() < 0.8:
        return T
    return int(rng.choice([F, L, R, T], p=[0.55, 0.18, 0.18, 0.09]))


def events(before: State, after: State) -> set[str]:
    happened = set()
    if (after.triaged & ~before.triaged).any():
        happened.add("triage")
    if ((after.progress > before.progress) & ~after.triaged).any():
        happened.add("progress")
    if (before.rubble & ~after.rubble).any():
        happened.add("clear")
    if (after.dead & ~before.dead).any():
        happened.add("dead")
    return happened


# -- 1. the env steps as the model does ------------------------------------------------------------
@pytest.mark.parametrize("case", CASES, ids=str)
def test_env_attributes_are_the_contracts(case):
    env, model, reset, _ = build(case)
    assert (env.n_agents, env.n_victims) == (model.n_agents, model.n_victims)
    for name, dtype in (("roles", np.int32), ("victim_kind", np.int32), ("blocked", bool), ("victim_pos", np.int32)):
        value = np.asarray(getattr(env, name))
        assert value.dtype == dtype, name
        np.testing.assert_array_equal(value, getattr(model, name), err_msg=name)
    for name in ("horizon", "triage_reward", "step_penalty", "start_dir", "critical_reward", "triage_steps",
                 "critical_triage_steps", "critical_expires", "view_radius"):
        assert getattr(env, name) == getattr(model, name), name
    assert env.layout.name == case.name

    _, state = reset(jax.random.PRNGKey(0))
    dtypes = {"agent_pos": np.int32, "agent_dir": np.int32, "triaged": bool, "t": np.int32, "victim_pos": np.int32,
              "rubble": bool, "progress": np.int32, "dead": bool, "seen": bool}
    for name, dtype in dtypes.items():
        assert np.asarray(getattr(state, name)).dtype == dtype, name


@pytest.mark.parametrize("case", CASES, ids=str)
def test_env_steps_as_the_model_does(case):
    env, model, reset, step = build(case)
    happened = collections.Counter()
    for seed in range(N_SEEDS):
        key, reset_key = jax.random.split(jax.random.PRNGKey(seed))
        _, env_state = reset(reset_key)
        state = model.reset(np.asarray(env_state.victim_pos))  # checks the draw too
        assert_same(state, env_state, f"{case} seed {seed} at reset")
        rng, done = np.random.default_rng(seed), False
        while not done:
            actions = [biased_action(rng, model, state, agent) for agent in range(model.n_agents)]
            key, step_key = jax.random.split(key)
            _, env_state, env_reward, env_done, _ = step(step_key, env_state, jnp.asarray(actions, jnp.int32))
            next_state, reward, done = model.step(state, actions)
            where = f"{case} seed {seed}, step from t={state.t}, actions {actions}"
            assert_same(next_state, env_state, where)
            assert np.float32(reward) == np.float32(env_reward), f"{where}: reward model {reward}, env {float(env_reward)}"
            assert done == bool(env_done), f"{where}: done model {done}, env {bool(env_done)}"
            happened.update(events(state, next_state))
            state = next_state
    assert case.expect <= set(happened), f"the rollouts never produced {sorted(case.expect - set(happened))}"


# -- 2. victims drawn at reset ---------------------------------------------------------------------
def test_reset_draws_victims_among_the_question_marks():
    env, model, *_ = build(DRAWN_CASE)
    _, states = jax.device_get(jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 256)))
    victim_pos = np.asarray(states.victim_pos)  # [keys, victims, 2]
    n_fixed = len(model.fixed_victim_pos)
    np.testing.assert_array_equal(env.victim_kind, [REGULAR, REGULAR, REGULAR, CRITICAL])  # the fixed V, then drawn: regular first
    np.testing.assert_array_equal(env.victim_pos[n_fixed:], -1)
    for i, placement in enumerate(victim_pos):
        assert_same(model.reset(placement), jax.tree.map(lambda x: x[i], states), f"key {i}")  # fixed ones kept, drawn ones distinct '?' cells
    drawn = [tuple(map(tuple, placement[n_fixed:])) for placement in victim_pos]
    assert len(set(drawn)) > 30  # 5 * 4 * 3 = 60 ordered placements
    question_marks = set(map(tuple, model.draw_cells.tolist()))
    assert set(map(tuple, victim_pos[:, n_fixed:].reshape(-1, 2).tolist())) == question_marks
    for slot in range(n_fixed, model.n_victims):  # each victim uniform on its own, not e.g. the critical one always last
        assert set(map(tuple, victim_pos[:, slot].tolist())) == question_marks, f"victim {slot} is not drawn on every '?' cell"


def test_view_observation_does_not_depend_on_where_an_unseen_victim_is():
    env, model, reset, _ = build(DRAWN_CASE)  # observation: view
    _, state = reset(jax.random.PRNGKey(0))
    state = state.replace(seen=jnp.zeros_like(state.seen))  # no victim seen yet
    obs = jax.tree.leaves(env.observe(state))
    victim_pos = np.asarray(state.victim_pos)
    for cell in model.draw_cells:
        if (victim_pos == cell).all(axis=1).any():
            continue
        moved = victim_pos.copy()
        moved[-1] = cell  # the critical victim, to a free '?' cell
        moved_obs = jax.tree.leaves(env.observe(state.replace(victim_pos=jnp.asarray(moved, jnp.int32))))
        for a, b in zip(obs, moved_obs, strict=True):
            np.testing.assert_array_equal(a, b, err_msg=f"an unseen victim moved to {cell.tolist()} shows in the view")


# -- 3. targeted rules, on the model and on the env -------------------------------------------------
class ModelWorld:
    def __init__(self, layout: str, regions: str, **params):
        self.model = Model.from_texts(layout, regions, **params)

    def reset(self, dirs=None) -> State:
        self.state = self.model.reset()
        if dirs is not None:
            self.state.agent_dir = np.asarray(dirs)
        return self.state

    def step(self, actions) -> tuple[State, float, bool]:
        self.state, reward, done = self.model.step(self.state, actions)
        return self.state, reward, done


@functools.lru_cache(maxsize=None)
def jitted_env(layout: str, regions: str, params: tuple):
    env = envs.make(envs.parse_layout(layout, regions, "targeted"), **dict(params))
    return env, jax.jit(env.step)


class EnvWorld:
    def __init__(self, layout: str, regions: str, **params):
        self.env, self._step = jitted_env(layout, regions, tuple(sorted(params.items())))

    def reset(self, dirs=None) -> State:
        _, self.state = self.env.reset(jax.random.PRNGKey(0))
        if dirs is not None:
            self.state = self.state.replace(agent_dir=jnp.asarray(dirs, jnp.int32))
        return State.of(jax.device_get(self.state))

    def step(self, actions) -> tuple[State, float, bool]:
        _, self.state, reward, done, _ = self._step(jax.random.PRNGKey(0), self.state, jnp.asarray(actions, jnp.int32))
        return State.of(jax.device_get(self.state)), float(reward), bool(done)


@pytest.fixture(params=["model", "env"])
def world(request):
    return {"model": ModelWorld, "env": EnvWorld}[request.param]


def one_region(layout: str) -> str:
    rows = layout.split("---\n")[-1].splitlines()
    return "R all hall\n---\n" + "\n".join("".join("#" if ch in "#X" else "R" for ch in row) for row in rows)


def picture(text: str) -> np.ndarray:
    """bool[H, W]: the 'o' cells of a picture."""
    return np.array([[ch == "o" for ch in row] for row in text.split()])


DOOR_ENGINEER_FIRST = ".E..\n#r##\n.A.V"  # engineer (0, 1) above the rubble, medic (2, 1) below
DOOR_MEDIC_FIRST = ".A..\n#r##\n.E.V"
DOOR_REGIONS = "T top room\nB bottom room\n---\nTTTT\n#T##\nBBBB"


def test_rubble_cleared_by_agent_0_lets_agent_1_through_in_the_same_step(world):
    w = world(DOOR_ENGINEER_FIRST, DOOR_REGIONS)
    w.reset(dirs=[SOUTH, NORTH])
    state, reward, done = w.step([T, F])
    assert not state.rubble.any()
    assert state.agent_pos.tolist() == [[0, 1], [1, 1]]
    assert (reward, done, state.t) == (0.0, False, 1)


def test_rubble_cleared_by_agent_1_lets_agent_0_through_only_on_the_next_step(world):
    w = world(DOOR_MEDIC_FIRST, DOOR_REGIONS)
    w.reset(dirs=[SOUTH, NORTH])
    state, *_ = w.step([F, T])
    assert not state.rubble.any() and state.agent_pos.tolist() == [[0, 1], [2, 1]]
    state, *_ = w.step([F, L])
    assert state.agent_pos.tolist() == [[1, 1], [2, 1]]


def test_a_medic_facing_rubble_does_nothing_and_cannot_pass(world):
    w = world(DOOR_MEDIC_FIRST, DOOR_REGIONS)
    w.reset(dirs=[SOUTH, EAST])
    for actions in ([T, L], [F, L]):
        state, reward, _ = w.step(actions)
        assert state.rubble.tolist() == [[False] * 4, [False, True, False, False], [False] * 4]
        assert state.agent_pos.tolist() == [[0, 1], [2, 1]]
        assert state.progress.tolist() == [0] and reward == 0.0


def test_an_engineer_facing_a_victim_does_nothing(world):
    layout = "EV.\nA.."  # engineer (0, 0) faces the victim; the medic (1, 0) faces the engineer
    w = world(layout, one_region(layout))
    w.reset(dirs=[EAST, NORTH])
    state, reward, done = w.step([T, T])
    assert state.progress.tolist() == [0] and state.triaged.tolist() == [False]
    assert (reward, done) == (0.0, False)


# Agent (0, 0) faces a critical victim (0, 1); a regular one at (1, 2) keeps the episode going.
CRITICAL_AHEAD = "AC.\n..V"


@pytest.mark.parametrize("steps, expires", [(1, 1), (2, 2), (3, 3)])
def test_a_critical_victim_triaged_on_the_step_it_would_expire_is_saved(world, steps, expires):
    w = world(CRITICAL_AHEAD, one_region(CRITICAL_AHEAD), critical_triage_steps=steps, critical_expires=expires)
    w.reset(dirs=[EAST])
    for k in range(1, steps + 1):
        state, reward, done = w.step([T])
        assert state.progress.tolist() == [k, 0]
    assert state.t == expires  # triage comes before t += 1 and the expiry test
    assert state.triaged.tolist() == [True, False] and state.dead.tolist() == [False, False]
    assert (reward, done) == (300.0, False)


def test_a_critical_victim_expires_when_t_reaches_critical_expires(world):
    w = world(CRITICAL_AHEAD, one_region(CRITICAL_AHEAD), critical_triage_steps=2, critical_expires=2)
    w.reset(dirs=[EAST])
    state, *_ = w.step([T])
    assert state.dead.tolist() == [False, False] and state.progress.tolist() == [1, 0]
    state, reward, done = w.step([L])
    assert state.dead.tolist() == [True, False]  # a regular victim never expires
    assert state.triaged.tolist() == [False, False] and (reward, done) == (0.0, False)


def test_a_dead_victim_still_blocks_and_cannot_be_triaged(world):
    w = world(CRITICAL_AHEAD, one_region(CRITICAL_AHEAD), critical_expires=1)
    w.reset(dirs=[EAST])
    state, *_ = w.step([F])
    assert state.dead.tolist() == [True, False] and state.agent_pos.tolist() == [[0, 0]]
    for action in (T, F, T):
        state, reward, done = w.step([action])
        assert state.agent_pos.tolist() == [[0, 0]]
        assert state.progress.tolist() == [0, 0] and state.triaged.tolist() == [False, False]
        assert (reward, done) == (0.0, False)


# Agent (0, 1) between a critical victim (0, 0), victim 0, and a regular one (0, 2), victim 1.
BETWEEN = "CAV"


def test_done_when_every_victim_is_triaged_or_dead(world):
    w = world(BETWEEN, one_region(BETWEEN), critical_expires=1)
    w.reset(dirs=[EAST])
    state, reward, done = w.step([T])
    assert state.triaged.tolist() == [False, True] and state.dead.tolist() == [True, False]
    assert (reward, done) == (100.0, True)


def test_done_when_every_victim_is_triaged(world):
    w = world(BETWEEN, one_region(BETWEEN))
    w.reset(dirs=[EAST])
    assert w.step([T])[1:] == (100.0, False)
    assert w.step([L])[1:] == (0.0, False)
    assert w.step([L])[1:] == (0.0, False)
    state, reward, done = w.step([T])
    assert state.triaged.tolist() == [True, True] and (reward, done, state.t) == (300.0, True, 4)


def test_done_at_the_horizon(world):
    w = world(BETWEEN, one_region(BETWEEN), horizon=2)
    w.reset()
    assert w.step([L])[2] is False
    assert w.step([L])[2] is True


@pytest.mark.parametrize("step_penalty", [0.0, -0.5])
def test_triage_needs_triage_steps_actions_and_then_stops_counting(world, step_penalty):
    layout = "AV.\n..V"
    w = world(layout, one_region(layout), triage_steps=2, step_penalty=step_penalty)
    w.reset(dirs=[EAST])
    expected = [([1, 0], [False, False], 0.0), ([2, 0], [True, False], 100.0), ([2, 0], [True, False], 0.0)]
    for progress, triaged, reward in expected:
        state, got_reward, done = w.step([T])
        assert state.progress.tolist() == progress and state.triaged.tolist() == triaged
        assert (got_reward, done) == (reward + step_penalty, False)


def test_two_medics_on_one_critical_victim_add_up_within_a_step(world):
    layout = "ACA.V"
    w = world(layout, one_region(layout), critical_triage_steps=2)
    w.reset(dirs=[EAST, WEST])
    state, reward, done = w.step([T, T])
    assert state.progress.tolist() == [2, 0] and state.triaged.tolist() == [True, False]
    assert (reward, done) == (300.0, False)  # paid once


@pytest.mark.parametrize("dirs, expected", [
    ([EAST, EAST], [[0, 1], [0, 3]]),  # agent 0 acts first and still finds agent 1 in its way
    ([WEST, WEST], [[0, 0], [0, 1]]),  # agent 1 follows into the cell agent 0 just left
])
def test_medics_block_each_other_in_index_order(world, dirs, expected):
    layout = ".AA.\nV..."
    w = world(layout, one_region(layout))
    w.reset(dirs=dirs)
    assert w.step([F, F])[0].agent_pos.tolist() == expected


# Two regions joined by a doorway at (2, 4); agent 0 at (2, 3) on the left, agent 1 at (3, 8) on the right.
SEEN = "V...#....\n....#....\n...A.....\n....#...A"
SEEN_REGIONS = "L left room\nR right room\n---\nLLLL#RRRR\nLLLL#RRRR\nLLLLRRRRR\nLLLL#RRRR"


@pytest.mark.parametrize("view_radius, expected", [
    (0, "......... ......... ...o..... ........o"),
    (1, "......... ..oo..... ..oo...oo ..oo...oo"),
    (2, ".ooo..... .ooo..ooo .ooo..ooo .ooo..ooo"),  # not (2, 4) nor (2, 5): the right room's
    (None, "oooo.oooo oooo.oooo ooooooooo oooo.oooo"),
])
def test_seen_at_reset_is_what_the_starts_see_in_their_own_regions(world, view_radius, expected):
    w = world(SEEN, SEEN_REGIONS, view_radius=view_radius)
    np.testing.assert_array_equal(w.reset().seen, picture(expected))


def test_seen_grows_with_what_each_agent_sees_in_its_own_region(world):
    w = world(SEEN, SEEN_REGIONS, view_radius=2)
    w.reset(dirs=[EAST, NORTH])
    state, *_ = w.step([F, L])  # agent 0 steps into the doorway, the right room's
    assert state.agent_pos.tolist() == [[2, 4], [3, 8]]
    np.testing.assert_array_equal(state.seen, picture(".ooo.oo.. .ooo.oooo .oooooooo .ooo.oooo"))
