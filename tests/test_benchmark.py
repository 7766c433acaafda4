"""jaxusar benchmark: the task suite's ids, the scores, env-step accounting and one tiny run end to end."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from jaxusar.cli import main
from jaxusar.config import ConfigError
from jaxusar.experiments import benchmark, suite


# -- the suite ---------------------------------------------------------------------------------------
def test_every_task_has_a_versioned_id_and_the_default_is_the_latest_of_each():
    ids = [t.id for t in suite.resolve(None)]
    assert "two_rooms-v1" in ids and "minimap-v1" in ids and len(ids) == len({i.rsplit("-v", 1)[0] for i in ids})
    assert all(suite.TASKS[i].id == i for i in suite.TASKS)


@pytest.mark.parametrize("ids, message", [
    (["two_rooms-v9"], "unknown task version 'two_rooms-v9'; two_rooms has two_rooms-v1"),
    (["kitchen-v1"], "unknown task 'kitchen-v1'; tasks: two_rooms-v1"),
    (["two_rooms-v1", "two_rooms-v1"], "--tasks names a task twice"),
])
def test_bad_task_ids_are_one_line_errors(ids, message):
    with pytest.raises(ConfigError, match="^" + message.replace("(", r"\(")):
        suite.resolve(ids)


def test_a_generated_task_refuses_a_generator_that_draws_another_map(tmp_path):
    task = suite.TASKS["gen_9x13-v1"]
    assert suite.materialize(task, tmp_path).endswith("gen_9x13.txt")
    assert (tmp_path / "gen_9x13.regions.txt").exists()
    changed = suite.Task(**{**task.__dict__, "sha256": "0" * 64})
    with pytest.raises(ConfigError, match="the generator now draws another map"):
        suite.materialize(changed, tmp_path)


# -- scores ------------------------------------------------------------------------------------------
def test_scores_are_one_at_the_reference_and_fall_with_steps_and_missed_victims():
    s = benchmark.episode_scores([300, 300, 200, 0], [24, 48, 300, 300], ref_return=300, ref_steps=24)
    np.testing.assert_allclose(s, [1.0, 0.5, 2 / 3 * 24 / 300, 0.0])
    np.testing.assert_allclose(benchmark.episode_scores([600, 300], [50, 80], ref_return=600), [1.0, 0.5])


def test_curves_keep_the_best_so_far_and_find_the_first_step_at_the_target():
    y = benchmark.best_so_far([[0.2, np.nan, 0.95, 0.5], [0.1, 0.3, 0.4, 0.6]])
    np.testing.assert_allclose(y, [[0.2, 0.2, 0.95, 0.95], [0.1, 0.3, 0.4, 0.6]])
    x = np.array([[10, 20, 30, 40], [10, 20, 30, 40]])
    assert benchmark.steps_to(x, y) == [30, None]
    np.testing.assert_allclose(benchmark.curve_on(np.array([5, 10, 35, 100]), x, y),
                               [[0, 0.2, 0.95, 0.95], [0, 0.1, 0.4, 0.6]])


# -- bad input ---------------------------------------------------------------------------------------
def test_an_algorithm_on_a_task_it_cannot_run_is_a_one_line_error_before_anything_compiles(tmp_path, capsys):
    argv = ["benchmark", "--tasks", "minimap-v1", "--algorithms", "hierarchical", "--out", str(tmp_path / "b"),
            "--set", "hierarchical.hierarchical.coordinator.kind=flat",
            "--set", "hierarchical.hierarchical.coordinator.max_joint_options=1000"]
    with pytest.raises(SystemExit, match="2"):
        main(argv)
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxusar benchmark: error: hierarchical cannot run minimap-v1: the flat coordinator on "
                          "'minimap' would choose among 3,375 joint options") and "\n" not in err
    assert not (tmp_path / "b").exists()


@pytest.mark.parametrize("argv, message", [
    (["--algorithms", "sarsa"], "unknown algorithm(s) 'sarsa'; the benchmark runs hierarchical, doc, iql, vdn, qmix, scripted"),
    (["--tasks", "two_rooms-v2"], "unknown task version 'two_rooms-v2'"),
])
def test_bad_benchmark_arguments(argv, message, tmp_path, capsys):
    with pytest.raises(SystemExit, match="2"):
        main(["benchmark", "--out", str(tmp_path / "b"), *argv])
    assert message in capsys.readouterr().err


# -- one tiny run, end to end ------------------------------------------------------------------------
TINY = ["train.episodes=4", "train.test_every=2", "train.chunk_steps=256", "dqn.hidden=[8]", "dqn.batch_size=4",
        "dqn.buffer_capacity=256", "dqn.learning_starts=0", "dqn.train_every=4"]


def test_a_tiny_benchmark_writes_its_leaderboard_figures_and_counts_env_steps(tmp_path, capsys):
    out = tmp_path / "bench"
    argv = ["benchmark", "--tasks", "two_rooms-v1", "gen_9x13-v1", "--algorithms", "iql", "vdn", "scripted", "--trials", "2",
            "--out", str(out), "--quiet", "--set", "env.horizon=40"] + [x for s in TINY for x in ("--set", s)]
    assert main(argv) == 0
    lines = capsys.readouterr().out.splitlines()  # each run's result lines, led by its task, task by task
    assert "[two_rooms-v1] [scripted] team steps [18, 18] against the optimum 18; optimal in 2 of 2 trials" in lines
    tagged = [line.split()[0] for line in lines if line.startswith("[two_rooms-v1] ") or line.startswith("[gen_9x13-v1] ")]
    assert tagged == sorted(tagged, key=["[two_rooms-v1]", "[gen_9x13-v1]"].index) and len(set(tagged)) == 2
    for name in ("leaderboard.md", "tasks.md", "results.json", "aggregates.png", "profile.png", "improvement.png",
                 "sample_efficiency.png"):
        assert (out / name).stat().st_size > 0, name
    results = json.loads((out / "results.json").read_text())
    assert set(results["algorithms"]) == {"iql", "vdn", "scripted"} and results["tasks"]["two_rooms-v1"]["reference"]["steps"] == 18
    board = (out / "leaderboard.md").read_text()
    assert "| iql | 2 |" in board and "| vdn | 2 |" in board
    # the scripted team learns nothing: its score from 0 env steps, the optimum on two_rooms
    scripted = results["runs"].pop("two_rooms-v1/scripted")
    assert scripted["final_score"] == [1.0, 1.0] and scripted["env_steps"] == [0, 0]
    assert scripted["env_steps_to_target"] == [0, 0] and "| scripted | 2 |" in board
    results["runs"].pop("gen_9x13-v1/scripted")
    for key, run in results["runs"].items():
        assert len(run["final_score"]) == 2 and all(0 <= s <= 1 for s in run["final_score"])
        # env steps: primitive actions of both medics over the training episodes (curves.csv's steps)
        rows = list(csv.DictReader(open(out / "runs" / f"{key}" / "curves.csv")))
        by_trial = [2 * sum(int(r["steps"]) for r in rows if r["kind"] == "train" and r["trial"] == str(k))
                    for k in range(2)]
        assert run["env_steps"] == by_trial, key
        assert np.all(np.diff(run["curve_env_steps"], axis=1) >= 0)
    assert (out / "runs" / "two_rooms-v1" / "iql" / "curves.png").stat().st_size > 0  # each run's own figures
    with pytest.raises(SystemExit, match="2"):  # a finished benchmark is never overwritten
        main(argv)
    assert "results.json exists" in capsys.readouterr().err


def test_quick_writes_the_suite_figures_and_each_runs_results_but_no_per_run_figures(tmp_path):
    out = tmp_path / "quick"
    sets = TINY + ["env.horizon=40", "hierarchical.dqn.train_every=1", "hierarchical.hierarchical.coordinator.episodes=2",
                   "hierarchical.hierarchical.coordinator.test_every=1"]
    argv = ["benchmark", "--quick", "--tasks", "two_rooms-v1", "--algorithms", "hierarchical", "iql", "scripted",
            "--trials", "2", "--out", str(out), "--quiet"] + [x for s in sets for x in ("--set", s)]
    assert main(argv) == 0
    assert (out / "aggregates.png").stat().st_size > 0 and json.loads((out / "results.json").read_text())["quick"]
    for algo in ("hierarchical", "iql", "scripted"):
        run = out / "runs" / "two_rooms-v1" / algo
        assert json.loads((run / "metrics.json").read_text())["trials"] == 2, algo
        assert not list(run.rglob("*.png")), algo
    assert (out / "runs" / "two_rooms-v1" / "hierarchical" / "params" / "trial_1.msgpack").exists()


def test_quick_budgets_configure_every_algorithm_including_the_untrained_scripted_team():
    from jaxusar.experiments import benchmark, suite

    cfgs = benchmark.configs(suite.TASKS["two_rooms-v1"], "two_rooms", quick=True, sets=[])
    assert set(cfgs) == set(benchmark.ALGORITHMS)
    assert cfgs["iql"].train.episodes == 100 and cfgs["hierarchical"].hierarchical.coordinator.episodes == 30
    assert cfgs["hierarchical"].train.episodes == 20
    assert not any(c.train.drop_finished for a, c in cfgs.items() if a != "scripted")  # too short to pay
    drawn = benchmark.configs(suite.TASKS["minimap-v1"], "minimap", quick=True, sets=[])  # victims drawn
    assert drawn["hierarchical"].train.episodes == 10 and drawn["iql"].train.episodes == 100
    assert benchmark.configs(suite.TASKS["minimap-v1"], "minimap", quick=False, sets=[])["hierarchical"].train.episodes \
        == 600  # the method's default
    assert benchmark.trial_count(None, quick=True) == 2 and benchmark.trial_count(None, quick=False) == 8
    assert benchmark.trial_count(3, quick=True) == 3  # --trials, when given, wins


def test_the_suites_time_to_go_counts_each_trainers_compiling(capsys):
    """A trainer with little to run still compiles: with the big one done, the small one's share of the
    work left is its TRAINER_COST, not ~0 (under --quick the time to go said 26 s with 194 s left)."""
    from types import SimpleNamespace as NS

    from jaxusar.experiments import benchmark, reproduce

    def stage(name, lanes, episodes):
        trainer = NS(cfg=NS(episodes=episodes), test_horizon=300, train_every=1, gradient_steps=1,
                     learner=NS(cfg=NS(batch_size=64)))
        return NS(name=name, keys=[None] * lanes, trainer=trainer)

    big, small = stage("big", 36, 20), stage("small", 2, 1)
    progress = benchmark.suite_progress([[big], [small]], quiet=False)
    progress("big", {"chunk": 1, "episodes_min": 20, "episodes_mean": 20.0, "episodes_total": 20, "elapsed": 1.0,
                     "eta": 0.0})
    line = capsys.readouterr().out.splitlines()[-1]
    cost = reproduce.expected_cost(big) + benchmark.TRAINER_COST
    share = cost / (cost + reproduce.expected_cost(small) + benchmark.TRAINER_COST)
    assert reproduce.expected_cost(small) < 0.01 * reproduce.expected_cost(big) and share < 0.95
    assert line.startswith(f"[benchmark] 1/2 trainers done ({share:.0%} of the expected work)"), line
    assert benchmark.suite_progress([[big]], quiet=True) is None


def test_threads_printing_inside_per_thread_each_get_their_own_lines_back(capsys):
    """benchmark.score_all scores pairs in threads; each pair's lines must come back whole, not interleaved."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from jaxusar.experiments import stdout

    turn = threading.Barrier(2)

    def one(name):
        with stdout.captured() as text:
            for line in range(3):
                print(f"{name} {line}")
                turn.wait(timeout=10)  # the other thread prints between this thread's lines
        return text.getvalue()

    with stdout.per_thread(), ThreadPoolExecutor(2) as pool:
        texts = list(pool.map(one, ["a", "b"]))
        print("main")
    assert texts == ["a 0\na 1\na 2\n", "b 0\nb 1\nb 2\n"]
    assert capsys.readouterr().out == "main\n"  # only what no thread captured reached stdout
