"""Rendering (ASCII and matplotlib), episode rollouts, the optimal plan, and the ``jaxusar demo`` CLI."""

import jax
import jax.numpy as jnp
import matplotlib.colors as mcolors
import matplotlib.image as mpimg
import numpy as np
import pytest

from jaxusar import envs
from jaxusar.cli import main
from jaxusar.envs import EAST, NORTH, SOUTH, WEST, make
from jaxusar.envs.render import (
    AGENT_COLOURS, CRITICAL_VICTIM, DEAD_VICTIM, MEDIC, RUBBLE_LINES, TRIAGED_CRITICAL, TRIAGED_VICTIM, VICTIM,
    ascii_legend, frame_indices, render_ascii, render_state, reset_state, rollout_states, save_episode_strip, save_map,
)
from jaxusar.planning import optimal_team_plan, optimal_team_steps

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
RESET_ASCII = """\
V...#.........^
....#..........
....#..........
...............
###............
.......XX...###
.......XX......
...............
...........#.V.
^..........#...
t=0 triaged=[0 0]"""


@pytest.fixture(scope="module")
def env():
    return make("two_rooms")


@pytest.fixture(scope="module")
def plan(env):
    return optimal_team_plan(env)


@pytest.fixture(scope="module")
def episode(env, plan):
    return rollout_states(env, plan)


def has_colour(path, colour, tol=0.02) -> bool:
    image = mpimg.imread(path)[..., :3]
    return bool(np.any(np.all(np.abs(image - np.asarray(mcolors.to_rgb(colour))) < tol, axis=-1)))


def assert_png(path):
    assert path.read_bytes()[:8] == PNG_MAGIC
    assert path.stat().st_size > 1000


# -- ASCII ----------------------------------------------------------------------------------------
def test_render_ascii_reset_state(env):
    _, state = env.reset(jax.random.key(0))
    assert render_ascii(env, state) == RESET_ASCII
    assert env.render_ascii(state) == RESET_ASCII


@pytest.mark.parametrize("direction, arrow", [(EAST, ">"), (SOUTH, "v"), (WEST, "<"), (NORTH, "^")])
def test_render_ascii_draws_facing_direction(env, direction, arrow):
    state = env.initial_state().replace(agent_dir=jnp.array([direction, NORTH]))
    assert render_ascii(env, state).splitlines()[0][14] == arrow


def test_triaged_victim_shows_plus(env, episode):
    states, rewards = episode
    first = int(np.argmax(rewards > 0)) + 1  # the state right after the first triage
    state = states[first]
    assert np.asarray(state.triaged).tolist() == [False, True]  # medic 0 triages the bottom victim first
    rows = render_ascii(env, state).splitlines()
    assert rows[8][13] == "+" and rows[0][0] == "V"
    assert rows[-1] == f"t={first} triaged=[0 1]"
    assert render_ascii(env, states[-1]).splitlines()[0][0] == "+"


def test_render_ascii_rejects_a_batch(env):
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), env.initial_state())
    with pytest.raises(ValueError, match="unbatched"):
        render_ascii(env, batch)


# -- rollouts and the optimal plan ------------------------------------------------------------------
def test_optimal_plan_triages_everyone_in_optimal_steps(env, plan):
    steps = optimal_team_steps(env)
    assert plan.shape == (steps, env.n_agents) and plan.dtype == np.int32
    step = jax.jit(env.step)
    state = env.initial_state()
    for t, actions in enumerate(plan):
        _, state, _, done, _ = step(None, state, actions)
        assert bool(done) == (t == steps - 1), f"done={bool(done)} after step {t + 1} of {steps}"
    assert np.all(state.triaged) and int(state.t) == steps


def test_rollout_states_stops_at_done(env, plan):
    extra = np.concatenate([plan, np.zeros((5, env.n_agents), np.int32)])
    states, rewards = rollout_states(env, extra)
    assert len(states) == len(plan) + 1 and rewards.shape == (len(plan),)
    assert rewards.sum() == env.n_victims * env.triage_reward
    assert render_ascii(env, states[0]) == RESET_ASCII


def test_rollout_states_checks_actions(env):
    with pytest.raises(ValueError, match="0..3"):
        rollout_states(env, [[0, 4]])
    with pytest.raises(ValueError, match="int\\[T, 2\\]"):
        rollout_states(env, [0, 1])


def test_frame_indices_keep_first_and_last():
    assert frame_indices(5, 12).tolist() == [0, 1, 2, 3, 4]
    keep = frame_indices(19, 12)
    assert len(keep) == 12 and keep[0] == 0 and keep[-1] == 18 and np.all(np.diff(keep) > 0)
    assert frame_indices(1, 12).tolist() == [0]


# -- pictures ---------------------------------------------------------------------------------------
def test_render_state_png(env, episode, tmp_path):
    path = tmp_path / "map.png"
    render_state(env, env.initial_state(), title="reset").figure.savefig(path)
    assert_png(path)
    assert has_colour(path, MEDIC) and has_colour(path, VICTIM) and has_colour(path, "#c0c0c0")
    assert not has_colour(path, TRIAGED_VICTIM)
    states, _ = episode
    render_state(env, states[-1]).figure.savefig(path)
    assert has_colour(path, TRIAGED_VICTIM) and not has_colour(path, VICTIM)


@pytest.mark.parametrize("batched", [False, True])
def test_save_episode_strip(env, episode, tmp_path, batched):
    states, rewards = episode
    if batched:  # one EnvState with a leading time axis
        states = jax.tree.map(lambda *xs: jnp.stack(xs), *states)
    path = save_episode_strip(env, states, tmp_path / "strip" / "episode.png", rewards=rewards, max_frames=6)
    assert path == tmp_path / "strip" / "episode.png"
    assert_png(path)
    assert has_colour(path, MEDIC) and has_colour(path, TRIAGED_VICTIM)  # the last frame is kept


def test_save_episode_strip_checks_inputs(env, episode, tmp_path):
    states, rewards = episode
    with pytest.raises(ValueError, match="rewards"):
        save_episode_strip(env, states, tmp_path / "x.png", rewards=rewards[:-1])
    with pytest.raises(ValueError, match="titles"):
        save_episode_strip(env, states, tmp_path / "x.png", titles=["a"])
    assert not (tmp_path / "x.png").exists()


# -- CLI --------------------------------------------------------------------------------------------
def test_demo_cli_end_to_end(env, tmp_path, capsys, monkeypatch):
    # The planner's jit cache is per env object: hand the CLI this module's env so the ~5 s compile is
    # shared with the plan fixture. Only the plain two_rooms map is redirected; the CLI path is unchanged.
    real_make = envs.make
    monkeypatch.setattr(envs, "make", lambda name, **kw: env if (name, kw) == ("two_rooms", {}) else
                        real_make(name, **kw))
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "USAREnv('two_rooms'" in stdout and RESET_ASCII in stdout
    assert "top_room -- hall_way" in stdout and "hall_way -- bottom_room" in stdout
    assert "(exact joint BFS): 18" in stdout
    assert "Return 200 in 18 steps (all victims triaged)" in stdout
    for name in ("map.png", "episode.png"):
        assert_png(out / name)
        assert str(out / name) in stdout


@pytest.mark.parametrize("argv, message", [
    (["demo", "--map", "no_such_map"], "unknown map 'no_such_map'"),
    (["demo", "--horizon", "-3"], "horizon=-3 is out of range"),
    (["demo", "--horizon", "0"], "horizon=0 is out of range"),
])
def test_demo_cli_bad_input_exits_2(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert message in err and err.startswith("jaxusar demo: error:")
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


@pytest.mark.parametrize("argv", [[], ["demo", "--horizon", "ten"], ["fly"]])
def test_cli_argument_errors_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert "error:" in capsys.readouterr().err


def test_demo_cli_unwritable_out(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(SystemExit) as exit_info:
        main(["demo", "--out", str(blocker / "sub")])
    assert exit_info.value.code == 2
    assert "cannot create the output folder" in capsys.readouterr().err


# -- contract part 2: rubble, engineers, critical, dead and drawn victims, what the team has seen ------------------
RUBBLE_RESET_ASCII = """\
V...#.........^
....#..........
....#..........
...............
###............
.......XX...###
.......XX...r..
............r..
...........#.V.
^....n.....#...
t=0 triaged=[0 0]"""


@pytest.fixture(scope="module")
def rubble_env():
    return make("two_rooms_rubble")


@pytest.fixture(scope="module")
def minimap():
    return make("minimap")


def test_render_ascii_rubble_and_engineers(rubble_env):
    state = rubble_env.initial_state()
    assert render_ascii(rubble_env, state) == RUBBLE_RESET_ASCII
    cleared = state.replace(rubble=state.rubble.at[6, 12].set(False))
    rows = render_ascii(rubble_env, cleared).splitlines()
    assert rows[6][12] == "," and rows[7][12] == "r"  # cleared (floor now) vs still there
    for direction, letter in zip((EAST, SOUTH, WEST, NORTH), "eswn"):  # engineers: the compass letter of their facing
        turned = state.replace(agent_dir=state.agent_dir.at[2].set(direction))
        assert render_ascii(rubble_env, turned).splitlines()[9][5] == letter
    legend = ascii_legend(rubble_env)
    assert "'>v<^' medics" in legend and "'eswn' engineer" in legend and "'r' rubble" in legend
    assert "',' rubble cleared" in legend and "' ' not seen" not in legend
    assert ascii_legend(make("two_rooms")) == ("'>v<^' medics facing E S W N, 'V' victim, '+' triaged, '#' wall, "
                                              "'X' obstacle")


def test_render_ascii_victims_where_the_state_draws_them(minimap):
    assert (minimap.victim_pos == -1).all()  # every victim of minimap is drawn at reset
    seen = []
    for k in range(2):
        state = reset_state(minimap, jax.random.key(k))
        rows = render_ascii(minimap, state, fog=False).splitlines()
        for v, (r, c) in enumerate(np.asarray(state.victim_pos)):
            assert rows[r][c] == "VC"[minimap.victim_kind[v]]
        assert sum(row.count("V") for row in rows[:-1]) == 6 and sum(row.count("C") for row in rows[:-1]) == 2
        assert "?" not in "".join(rows)  # the truth: the '?' cells without a victim are floor
        seen.append(np.asarray(state.victim_pos))
    assert not np.array_equal(*seen)  # another key, another draw


def test_render_ascii_triaged_dead_and_progress(minimap):
    state = reset_state(minimap)
    critical = np.flatnonzero(minimap.victim_kind == 1)
    state = state.replace(triaged=state.triaged.at[0].set(True).at[critical[0]].set(True),
                          progress=state.progress.at[0].set(1).at[critical[0]].set(2).at[critical[1]].set(1),
                          dead=state.dead.at[critical[1]].set(True), t=jnp.int32(61))
    rows = render_ascii(minimap, state, fog=False).splitlines()
    pos = np.asarray(state.victim_pos)
    assert rows[pos[0][0]][pos[0][1]] == "+" and rows[pos[critical[0]][0]][pos[critical[0]][1]] == "+"
    assert rows[pos[critical[1]][0]][pos[critical[1]][1]] == "x"
    assert rows[-1] == "t=61 triaged=[1 0 0 0 0 0 1 0] dead=[0 0 0 0 0 0 0 1] progress=[1 0 0 0 0 0 2 1]"


def test_render_ascii_fog_hides_unseen_victims(minimap):
    assert minimap.observation == "view"
    states = [reset_state(minimap, jax.random.key(k)) for k in range(3)]
    fogged = [render_ascii(minimap, s) for s in states]  # fog is the default on a "view" map
    assert fogged[0] == fogged[1] == fogged[2]  # nothing in it depends on where the unseen victims are
    rows = fogged[0].splitlines()
    for r, c in minimap.layout.random_cells:  # every '?' cell of the layout lies in a room nobody has seen yet
        assert rows[r][c] == "?"
    assert rows[0][1] == " " and rows[5][9] == "^" and rows[4][11] == "r" and rows[4][7] == "#"
    assert "V" not in fogged[0] and "C" not in fogged[0]
    # once the team has seen a room, its victims show and its empty '?' cells are floor
    state = states[0]
    top_west = minimap.graph.cell_region == minimap.graph.index("top_west")
    rows = render_ascii(minimap, state.replace(seen=state.seen | top_west)).splitlines()
    truth = render_ascii(minimap, state, fog=False).splitlines()
    for r, c in np.argwhere(top_west):
        assert rows[r][c] == truth[r][c]
    assert render_ascii(make("two_rooms", observation="view"), make("two_rooms").initial_state()) != RESET_ASCII


def test_part2_pictures(rubble_env, minimap, tmp_path):
    path = tmp_path / "x.png"
    state = rubble_env.initial_state()
    ax = render_state(rubble_env, state, legend=True)
    ax.figure.savefig(path)
    assert has_colour(path, RUBBLE_LINES)
    assert all(has_colour(path, colour) for colour in AGENT_COLOURS[:3])  # one colour per agent
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert {"medic 0", "medic 1", "engineer 2", "rubble", "rubble cleared"} <= set(labels)
    render_state(rubble_env, state.replace(rubble=jnp.zeros_like(state.rubble))).figure.savefig(path)
    assert not has_colour(path, RUBBLE_LINES)  # cleared: pebbles on the floor, no hatched cell

    state = reset_state(minimap)
    critical = np.flatnonzero(minimap.victim_kind == 1)
    render_state(minimap, state, fog=False).figure.savefig(path)
    assert has_colour(path, VICTIM) and has_colour(path, CRITICAL_VICTIM)
    render_state(minimap, state).figure.savefig(path)  # the team's view at reset: every victim unseen
    assert not has_colour(path, VICTIM) and not has_colour(path, CRITICAL_VICTIM)
    done = state.replace(triaged=state.triaged.at[critical[0]].set(True), dead=state.dead.at[critical[1]].set(True))
    ax = render_state(minimap, done, fog=False, legend=True)
    ax.figure.savefig(path)
    assert has_colour(path, TRIAGED_CRITICAL) and has_colour(path, DEAD_VICTIM)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert {"critical victim", "triaged critical", "dead"} <= set(labels)
    labels = [t.get_text() for t in render_state(minimap, state, legend=True).get_legend().get_texts()]
    assert {"not seen by the team", "not seen: may hold a victim"} <= set(labels)


def test_map_and_strip_of_a_map_with_drawn_victims(minimap, tmp_path):
    assert_png(save_map(minimap, tmp_path / "map.png"))  # no key needed: one draw, said in the title
    rng = np.random.default_rng(0)
    states, rewards = rollout_states(minimap, rng.integers(0, 4, (8, minimap.n_agents)), jax.random.key(1))
    assert np.array_equal(states[0].victim_pos, reset_state(minimap, jax.random.key(1)).victim_pos)
    path = save_episode_strip(minimap, states, tmp_path / "episode.png", rewards=rewards)
    assert_png(path) and has_colour(path, AGENT_COLOURS[2])


def write_map(path, layout: str) -> None:
    from jaxusar.envs.mapgen import segmented_regions_text

    path.write_text(layout)
    path.with_name(path.stem + ".regions.txt").write_text(segmented_regions_text(layout))


def test_demo_cli_with_an_engineer_plays_the_plan(tmp_path, capsys):
    """A map small enough for a quick exact search, where the medic waits for the engineer to clear rubble."""
    write_map(tmp_path / "tiny.txt", "A#..V\n.r...\nE#...\n")
    out = tmp_path / "demo"
    assert main(["demo", "--map", str(tmp_path / "tiny.txt"), "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "(exact joint BFS): 12" in stdout and "Return 100 in 12 steps (all victims triaged)" in stdout
    assert "medic 0     engineer 1  reward" in stdout and "CLEAR" in stdout
    assert "engineer 1 at (2, 0) facing NORTH: an engineer" in stdout
    assert "'eswn' engineer facing E S W N" in stdout
    for name in ("map.png", "episode.png"):
        assert_png(out / name)


def test_demo_cli_on_a_map_with_drawn_victims(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--map", "minimap", "--seed", "3", "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    drawn = reset_state(make("minimap"), jax.random.key(3))
    truth = render_ascii(make("minimap"), drawn, fog=False)
    assert "Reset state (victims drawn with --seed 3)" in stdout and truth in stdout
    assert "as the team has seen it (observation 'view'" in stdout and render_ascii(make("minimap"), drawn) in stdout
    assert "the planner below plans for this draw" in stdout
    assert "No plan to show (the exact search is out of reach on this map): playing a uniformly random policy " \
           "instead (--seed 3)." in stdout
    for name in ("map.png", "episode.png"):
        assert_png(out / name)
        assert f"Wrote {out / name}" in stdout


def test_demo_cli_says_when_a_picture_cannot_be_drawn(tmp_path, capsys, monkeypatch):
    from jaxusar.envs import render

    def broken(*args, **kwargs):
        raise OSError("disk full")
    monkeypatch.setattr(render, "save_episode_strip", broken)
    out = tmp_path / "demo"
    write_map(tmp_path / "one.txt", "A.V\n")
    assert main(["demo", "--map", str(tmp_path / "one.txt"), "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert f"jaxusar demo: error: could not draw {out / 'episode.png'}: disk full" in captured.err
    assert f"Wrote {out / 'map.png'}" in captured.out and not (out / "episode.png").exists()


def test_demo_cli_bad_seed(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["demo", "--seed", "-1"])
    assert exit_info.value.code == 2 and "--seed must be >= 0" in capsys.readouterr().err


def test_demo_region_table_columns_stay_aligned_past_region_9():
    from jaxusar.cli import region_lines

    env = envs.make("office")
    graph = env.graph
    assert graph.n_regions > 10
    lines = region_lines(graph, graph.victim_region, graph.cell_region[tuple(env.layout.agent_start.T)])
    assert len(lines) == graph.n_regions
    assert len({line.index(" cells") for line in lines}) == 1 and len({line.index("victims") for line in lines}) == 1
