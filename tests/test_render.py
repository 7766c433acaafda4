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
    MEDIC, TRIAGED_VICTIM, VICTIM, frame_indices, render_ascii, render_state, rollout_states,
    save_episode_strip,
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
