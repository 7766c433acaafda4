"""The scripted team: its routes, its play on the shipped maps, what it may know, and its judging."""

import json
from collections import deque

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxusar import envs, planning
from jaxusar.algos import scripted
from jaxusar.cli import main
from jaxusar.experiments.scripted import judging_keys


def bfs(targets: np.ndarray, passable: np.ndarray) -> np.ndarray:
    h, w = targets.shape
    dist = np.full((h, w), scripted.FAR)
    queue = deque(zip(*np.nonzero(targets)))
    dist[targets] = 0
    while queue:
        r, c = queue.popleft()
        for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
            nr, nc = r + dr, c + dc
            if 0 <= nr < h and 0 <= nc < w and passable[nr, nc] and not targets[nr, nc] and dist[nr, nc] == scripted.FAR:
                dist[nr, nc] = dist[r, c] + 1
                queue.append((nr, nc))
    return dist


def test_distance_to_is_a_breadth_first_search():
    rng = np.random.default_rng(0)
    for _ in range(5):
        passable = rng.random((9, 13)) < 0.7
        targets = rng.random((9, 13)) < 0.04
        np.testing.assert_array_equal(np.asarray(scripted.distance_to(jnp.asarray(targets), jnp.asarray(passable))),
                                      bfs(targets, passable))


def play(env, trials=2):
    resets = judging_keys(env)
    run = jax.vmap(jax.vmap(lambda r, k: scripted.rollout(env, r, k), (0, None)), (None, 0))
    return jax.device_get(jax.jit(run)(resets, jax.random.split(jax.random.PRNGKey(1), trials)))


def test_the_scripted_team_saves_everyone_on_fixed_maps():
    # two_rooms: each medic to the victim nearest it is the paper's optimum; two_rooms_rubble: the bottom
    # victim is walled in by rubble until the engineer has cleared it
    env = envs.make("two_rooms", horizon=300)
    out = play(env)
    assert (out["steps"] == planning.team_reference(env)["steps"]).all() and (out["return"] == 200).all()
    out = play(envs.make("two_rooms_rubble", horizon=300))
    assert (out["saved"] == 2).all() and (out["steps"] < 300).all()


def test_the_scripted_team_does_not_see_unseen_victims():
    # under "view" its actions are the same wherever an unseen victim lies (the env's no-leak property)
    env = envs.make("minimap")
    _, state = env.reset(jax.random.PRNGKey(3))
    seen = np.asarray(state.seen)
    pos = np.asarray(state.victim_pos)
    hidden = [v for v in range(env.n_victims) if not seen[tuple(pos[v])]]
    taken = {tuple(p) for p in pos}
    free = [tuple(c) for c in env.layout.random_cells if not seen[tuple(c)] and tuple(c) not in taken]
    assert hidden and free
    moved = state.replace(victim_pos=state.victim_pos.at[hidden[0]].set(jnp.asarray(free[0])))
    act = jax.jit(lambda s, k: scripted.act(env, s, k))
    for k in jax.random.split(jax.random.PRNGKey(0), 8):
        np.testing.assert_array_equal(act(state, k), act(moved, k))
    # and it does act on a victim it has seen: one next to a medic changes what that medic does
    medic = int(np.flatnonzero(env.roles == 0)[0])
    r, c = np.asarray(state.agent_pos[medic])
    beside = next((r + dr, c + dc) for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0))
                  if not env.blocked[r + dr, c + dc] and (r + dr, c + dc) not in taken
                  and not (np.asarray(state.agent_pos) == (r + dr, c + dc)).all(-1).any())
    near = state.replace(victim_pos=state.victim_pos.at[hidden[0]].set(jnp.asarray(beside)))
    assert any((act(near, k)[medic] != act(state, k)[medic]) for k in jax.random.split(jax.random.PRNGKey(0), 8))


def test_train_scripted_judges_drawn_worlds_against_the_clairvoyant_reference(tmp_path, capsys):
    main(["train", "scripted", "--map", "minimap", "--trials", "2", "--out", str(tmp_path / "s")])
    m = json.loads((tmp_path / "s" / "metrics.json").read_text())
    env = envs.make("minimap")
    ref = planning.clairvoyant_reference(env, n_draws=32, seed=0)
    assert m["draws"] == 32 and m["reference_return"] == pytest.approx(ref["return"])
    assert m["normalized_score"] == pytest.approx(np.asarray(m["mean_return"]) / ref["return"], abs=1e-4)
    assert 0 < m["normalized"]["median"] < 1 and m["normalized"]["best"] == pytest.approx(max(m["normalized_score"]), abs=1e-4)
    assert all(0 <= f <= 1 for f in m["fraction_all_saved"]) and m["critical_victims"] == 2
    assert (tmp_path / "s" / "team_episode.png").exists()
    assert "normalized score over 32 draws" in capsys.readouterr().out


def test_train_scripted_on_a_map_with_no_medic_is_one_line(tmp_path, capsys):
    from jaxusar.envs.layout import layout_path

    src = layout_path("two_rooms_rubble")
    (tmp_path / "eng.txt").write_text(src.read_text().replace("A", "E"))
    (tmp_path / "eng.regions.txt").write_text(src.with_suffix(".regions.txt").read_text())
    with pytest.raises(SystemExit) as e:
        main(["train", "scripted", "--map", str(tmp_path / "eng.txt"), "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "no medic" in err[0] and not (tmp_path / "x").exists()


def test_the_scripted_experiment_plays_each_set_of_draws_once(monkeypatch):
    """``finish`` and a benchmark's scoring judge the same draws: the second asks for what the first played."""
    from jaxusar import algos, config
    from jaxusar.experiments.scripted import Experiment

    exp = Experiment(config.load(None, ["env.map=two_rooms"], defaults=algos.defaults("scripted")),
                     jax.random.split(jax.random.PRNGKey(0), 2))
    traced, rollout = [], scripted.rollout
    monkeypatch.setattr(scripted, "rollout", lambda *a, **k: traced.append(1) or rollout(*a, **k))
    first = exp.play(judging_keys(exp.env))
    assert exp.play(judging_keys(exp.env)) is first and len(traced) == 1
    other = exp.play(jax.random.split(jax.random.PRNGKey(7), 3))
    assert len(traced) == 2 and other["return"].shape == (2, 3) and first["return"].shape == (2, 1)
