"""End-to-end runs through the CLI: outputs written, refusing to overwrite, bad input rejected early."""

import csv
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxusar.cli import main
from jaxusar.experiments.plots import kept

IQL_TINY = ["--set", "train.episodes=20", "--set", "train.test_every=10", "--set", "train.chunk_steps=2000",
            "--set", "env.horizon=100"]


def test_train_iql_end_to_end(tmp_path, capsys):
    out = tmp_path / "iql"
    assert main(["train", "iql", "--trials", "2", "--out", str(out)] + IQL_TINY) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["algorithm"] == "iql" and m["trials"] == 2 and len(m["episodes_to_optimal"]) == 2
    assert m["optimal_team_steps"] == 18 and m["config"]["train"]["episodes"] == 20 and m["wall_seconds"] > 0
    rows = list(csv.DictReader(open(out / "curves.csv")))
    assert sum(r["kind"] == "train" for r in rows) == 2 * 20 and sum(r["kind"] == "test" for r in rows) == 2 * 2
    assert all(int(r["steps"]) <= 100 for r in rows)
    assert (out / "params" / "trial_1.msgpack").stat().st_size > 0
    assert (out / "curves.png").read_bytes()[:4] == b"\x89PNG"
    printed = capsys.readouterr().out
    assert "episodes done 20/20 in the slowest trial" in printed  # progress was shown
    assert "optimal in 0 of 2 trials (never within 20 episodes)" in printed and "None" not in printed
    # a finished run is never overwritten without --force
    with pytest.raises(SystemExit) as e:
        main(["train", "iql", "--trials", "2", "--out", str(out)] + IQL_TINY)
    assert e.value.code == 2 and "--force" in capsys.readouterr().err


def test_progress_gives_no_time_to_go_before_the_slowest_trial_has_moved(capsys):
    """A chunk that ends no episode of the slowest trial (a resumed run starts part-way) has no pace to
    extrapolate: the line says so instead of dividing by almost zero."""
    from jaxusar.core.trainer import seconds_to_go
    from jaxusar.experiments.train import print_progress

    assert seconds_to_go(10.0, 0.2, 0.2) is None and seconds_to_go(10.0, 0.0, 0.0) is None
    assert seconds_to_go(10.0, 0.2, 0.4) == pytest.approx(30.0)  # 0.2 in 10 s; 0.6 left
    line = {"chunk": 1, "episodes_min": 0, "episodes_total": 4, "episodes_mean": 0.0, "elapsed": 0.4}
    print_progress("x", {**line, "eta": None})
    print_progress("x", {**line, "eta": 30.2})
    first, second = capsys.readouterr().out.splitlines()
    assert first.endswith("0 s elapsed, time to go not known yet") and second.endswith("about 30 s to go")


@pytest.mark.parametrize("argv, message", [
    (["train", "iql", "--set", "dqn.gamma=2"], "dqn.gamma"),
    (["train", "iql", "--set", "train.nope=1"], "train.nope"),
    (["train", "iql", "--trials", "0"], "--trials"),
    (["train", "sarsa"], "unknown algorithm"),
    (["train", "iql", "--set", "env.map=atlantis"], "unknown map"),
    (["train", "iql", "--map", "nowhere/my_map.txt"], "the map file 'nowhere/my_map.txt' does not exist"),
    (["train", "iql", "--set", "env.map=my_map.txt"], "the map file 'my_map.txt' does not exist"),
    (["train", "iql", "--options", "2,4"], "--options"),
    (["train", "doc", "--options", "2,x"], "--options"),
    (["train", "iql", "--config", "/nonexistent.yaml"], "does not exist"),
    (["train", "iql", "--set", "dqn.n_step_cut_exploring=true", "--set", "dqn.n_step_cut_greedy=true"],
     "n_step_cut_greedy"),
])
def test_train_bad_input_is_one_line_before_compiling(argv, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv + ["--out", str(tmp_path / "x" / "y")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and message in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()  # a refused run leaves no empty folder behind


def test_the_default_folder_names_the_algorithm_and_the_map(tmp_path, monkeypatch, capsys):
    """Runs of one algorithm on two maps do not collide; a finished run in the way suggests --out."""
    from jaxusar import config
    from jaxusar.experiments.train import default_out

    assert default_out(config.load()) == Path("runs/iql-two_rooms")
    assert default_out(config.load(sets=["env.map=office", "algo=doc"])) == Path("runs/doc-office")
    (tmp_path / "my_ward.txt").write_text(OFFICE)
    assert default_out(config.load(sets=[f"env.map={tmp_path / 'my_ward.txt'}"])) == Path("runs/iql-my_ward")
    monkeypatch.chdir(tmp_path)
    Path("runs/iql-two_rooms").mkdir(parents=True)
    Path("runs/iql-two_rooms/metrics.json").write_text("{}")
    with pytest.raises(SystemExit) as e:
        main(["train", "iql"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "runs/iql-two_rooms/metrics.json exists" in err
    assert "--out DIR" in err and "--force" in err
    assert sorted(p.name for p in Path("runs").iterdir()) == ["iql-two_rooms"]


def test_a_refused_run_removes_only_the_folders_it_made(tmp_path):
    from jaxusar.experiments.train import removed_if_refused

    (tmp_path / "mine" / "kept").mkdir(parents=True)
    with pytest.raises(KeyboardInterrupt):
        with removed_if_refused(tmp_path / "mine"):
            for d in ("checkpoints", "iql", "doc/K2"):
                (tmp_path / "mine" / d).mkdir(parents=True)
            (tmp_path / "mine" / "iql" / "curves.csv").write_text("")
            raise KeyboardInterrupt
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["iql", "kept"]  # the user's, and one written to
    with pytest.raises(ValueError):
        with removed_if_refused(tmp_path / "new" / "run"):
            (tmp_path / "new" / "run" / "checkpoints").mkdir(parents=True)
            raise ValueError
    assert not (tmp_path / "new").exists()


# Ctrl-C at a known moment: the child sends itself SIGINT right after its first checkpoint is on disk.
CTRL_C_AFTER_THE_FIRST_CHECKPOINT = """
import os, signal, sys
from jaxusar.cli import main
from jaxusar.core import checkpoint

save = checkpoint.save
# Python's own Ctrl-C handler, whatever this process inherited (a test runner's worker may ignore SIGINT)
signal.signal(signal.SIGINT, signal.default_int_handler)

def save_then_ctrl_c(path, tree, meta):
    save(path, tree, meta)
    checkpoint.save = save
    os.kill(os.getpid(), signal.SIGINT)

checkpoint.save = save_then_ctrl_c
sys.exit(main(sys.argv[1:]))
"""


def test_ctrl_c_is_one_line_and_the_same_command_resumes_saying_from_where(tmp_path, capsys):
    import subprocess

    out = tmp_path / "run"
    ckpt = out / "checkpoints" / "iql.ckpt"
    argv = ["train", "iql", "--trials", "2", "--out", str(out), "--checkpoint-every", "0", *IQL_TINY,
            "--set", "train.chunk_steps=500"]
    done = subprocess.run([sys.executable, "-c", CTRL_C_AFTER_THE_FIRST_CHECKPOINT, *argv], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 130 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.splitlines()[-1] == (f"jaxusar train: interrupted; the last checkpoint is {ckpt} (iql after "
                                            "chunk 1); the same command resumes from there")
    assert ckpt.exists() and not (out / "metrics.json").exists()
    assert main(argv) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith(f"[iql] resumed from {ckpt}: continuing after chunk 1 ("), first
    assert json.loads((out / "metrics.json").read_text())["seconds"]["resumed_from_chunk"] == 1


# A second map (the README's example): no room called "bottom", so the two-rooms map's settings must not
# leak onto it; small, so that its planner and figures take no time.
OFFICE = """\
V..#....#..V
.......A....
...#....#...
####....####
.....A......
"""
OFFICE_REGIONS = """\
L left_room room
H hall_way hall
R right_room room
---
LLL#HHHH#RRR
LLLHHHHHHRRR
LLL#HHHH#RRR
####HHHH####
HHHHHHHHHHHH
"""


def write_office(folder) -> str:
    (folder / "office.txt").write_text(OFFICE)
    (folder / "office.regions.txt").write_text(OFFICE_REGIONS)
    return str(folder / "office.txt")


def sets(*kvs: str) -> list[str]:
    return [arg for kv in kvs for arg in ("--set", kv)]


@pytest.mark.parametrize("navigation", ["chained", "goal"])
def test_the_listed_algorithms_are_the_registry_and_each_trains_from_the_cli(navigation, tmp_path, capsys):
    """What `jaxusar train --help` lists trains on a tiny budget: iql above, vdn and qmix in
    tests/test_value_decomposition.py, doc in tests/test_option_critic.py
    (test_runner_learns_to_triage_on_a_tiny_map_and_writes_results), and the paper's method here, with its
    default config (and with goal-conditioned navigation), on a map without the two-rooms map's task names."""
    from jaxusar import algos

    assert sorted(algos.registry()) == ["doc", "hierarchical", "iql", "qmix", "scripted", "vdn"]
    assert algos.registry()["hierarchical"].__name__ == "jaxusar.algos.coordinator"
    out = tmp_path / "hierarchical"
    assert main(["train", "hierarchical", "--trials", "1", "--out", str(out), "--quiet",
                 "--map", write_office(tmp_path)]
                + sets("train.episodes=20", "train.test_every=10", "train.chunk_steps=2000",
                       "hierarchical.coordinator.episodes=4", "hierarchical.coordinator.chunk_steps=4",
                       f"hierarchical.navigation={navigation}")) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert "chunk" not in printed  # --quiet: no progress lines, but the results
    assert "[hierarchical] budget per trial:" in printed and "[hierarchical] end to end" in printed
    assert f"wrote {out}" in printed
    m = json.loads((out / "metrics.json").read_text())
    assert m["config"]["algo"] == "hierarchical" and len(m["episodes_to_optimal"]) == 1
    assert m["config"]["env"]["map"].endswith("office.txt") and m["config"]["hierarchical"]["task_gamma"] == {}
    assert m["optimal_team_steps"] == 11
    if navigation == "chained":
        assert len(m["tasks"]) == 5  # navigation to each of 3 regions + 2 victims
    else:  # one navigation task for both rooms: from the 38 open cells outside each room, any facing
        assert m["tasks"][0] == "NAVIGATE-TO-ANY-ROOM" and len(m["tasks"]) == 3
        assert m["subpolicy_initiation_states"]["NAVIGATE-TO-ANY-ROOM"] == 4 * (38 + 38)
    assert 0 <= m["subpolicy_coverage"][m["tasks"][0]][0] <= 1
    assert "Traceback" not in captured.err
    written = {p.name for p in out.iterdir()}  # the figures `jaxusar train --help` names
    assert {"fig4_subpolicies.png", "coordinator.png", "team_episode.png"} <= written and "curves.png" not in written
    assert {f"fig4_{t.replace(':', '_').lower()}.png" for t in m["tasks"]} <= written


def test_train_help_names_the_figures_each_algorithm_writes(capsys):
    from jaxusar.experiments import doc, hierarchical
    from jaxusar.experiments.train import FlatExperiment

    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = capsys.readouterr().out
    for algo, cls in (("iql", FlatExperiment), ("doc", doc.Experiment), ("hierarchical", hierarchical.Experiment)):
        assert f"  {algo:<13} {', '.join(cls.FIGURES)}" in text
    assert "DIR/curves.png" not in text
    with pytest.raises(SystemExit):
        main(["maps", "--help"])
    assert "--out" not in [line for line in capsys.readouterr().out.splitlines() if "segment" in line][0]


def test_the_hierarchical_summary_says_what_the_budget_is_and_where_each_trial_stands():
    """The console's last lines after `train hierarchical` (issue: 'optimal in 0 of 2' end to end beside 'optimal
    in 1 of 2' for the coordinator read as a contradiction): the budget's parts, the sub-policies exact from
    every state, the best team episode against the optimum, then the two counts."""
    from jaxusar.experiments.hierarchical import summary_lines

    tasks = [f"task{k}" for k in range(9)]
    per_task = {t: [20, 20] for t in tasks}
    per_task["task3"] = [20, None]  # trial 1: one sub-policy not exact from every state
    metrics = {
        "tasks": tasks, "trials": 2, "optimal_team_steps": 24, "reference": "optimum",
        "subpolicy_episodes_to_optimal": {"per_task": per_task},
        "subpolicy_coverage": {t: [1.0, 1.0 if t != "task3" else 0.972] for t in tasks},
        "subpolicy_initiation_states": {t: 428 for t in tasks},
        "best_team_test_steps": [24, 26], "optimality_gap": [1.0, 26 / 24],
        "coordinator_episodes_to_optimal": [70, None], "episodes_to_optimal": [250, None],
        "episodes_to_optimal_single_start": [None, None],
    }
    lines = summary_lines(metrics, per_subpolicy=30, coordinator=100)
    assert lines[0] == "budget per trial: 9 sub-policies x 30 episodes + 100 coordinator episodes = 370 episodes"
    assert lines[1] == ("sub-policies greedy-optimal from every state they may start in: trial 0: 9/9, trial 1: 8/9; "
                        "the least: task3 in trial 1, optimal from 97.2% of its 428 states")
    assert lines[2].startswith("best greedy team episode (the coordinator over its trial's sub-policies): trial 0: "
                               "24 steps, trial 1: 26 steps; the optimum is 24 steps (exact joint search); 1 of 2")
    assert "optimal in 1 of 2 trials, after 70 episodes" in lines[3]
    assert lines[4].endswith("optimal in 1 of 2 trials, after 250 episodes; never within 370 in the other 1; "
                             "median > 370")
    many = {**metrics, "trials": 10, "best_team_test_steps": [24] * 9 + [300], "optimality_gap": [1.0] * 9 + [None],
            "subpolicy_episodes_to_optimal": {"per_task": {t: v * 5 for t, v in per_task.items()}},
            "subpolicy_coverage": {t: v * 5 for t, v in metrics["subpolicy_coverage"].items()},
            "coordinator_episodes_to_optimal": [70] * 10, "episodes_to_optimal": [250] * 10,
            "episodes_to_optimal_single_start": [None] * 10, "reference": "lower bound"}
    lines = summary_lines(many, per_subpolicy=30, coordinator=100)
    assert "all 9 in 5 of 10 trials, fewest 8/9" in lines[1]
    assert "every victim triaged in 9 of 10 trials, in 24 to 24 steps" in lines[2] and "lower bound is 24" in lines[2]


@pytest.mark.parametrize("name", ["options", "subpolicies", "coordinator", "option_critic"])
def test_modules_that_are_parts_of_an_algorithm_are_not_trainable(name, capsys):
    with pytest.raises(SystemExit) as e:
        main(["train", name])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "unknown algorithm" in err and "doc, hierarchical, iql, qmix, scripted, vdn" in err


def test_map_settings_apply_on_their_map_only(tmp_path, capsys):
    from jaxusar import algos, config

    defaults = algos.defaults("hierarchical")
    assert config.load(defaults=defaults).hierarchical.task_gamma == {"TRIAGE-BOTTOM-VICTIM": 0.9}  # two_rooms'
    path = write_office(tmp_path)
    assert config.load(None, [f"env.map={path}"], defaults).hierarchical.task_gamma == {}
    # a map's own settings file beside its layout; a config file and --set still override it; {} clears
    (tmp_path / "office.settings.yaml").write_text("hierarchical:\n  task_gamma: {TRIAGE-LEFT-VICTIM: 0.8}\n")
    assert config.load(None, [f"env.map={path}"], defaults).hierarchical.task_gamma == {"TRIAGE-LEFT-VICTIM": 0.8}
    cleared = config.load(None, [f"env.map={path}", "hierarchical.task_gamma={}"], defaults)
    assert cleared.hierarchical.task_gamma == {}
    (tmp_path / "office.settings.yaml").write_text("hierarchical:\n  task_gama: {}\n")
    with pytest.raises(config.ConfigError, match="office.settings.yaml.*task_gama"):
        config.load(None, [f"env.map={path}"], defaults)
    # an algorithms.<algo> section applies to that algorithm only; a wrong name or key there is named
    (tmp_path / "office.settings.yaml").write_text("algorithms:\n  iql: {train: {episodes: 70}}\n")
    assert config.load(None, [f"env.map={path}"], algos.defaults("iql")).train.episodes == 70
    assert config.load(None, [f"env.map={path}"], defaults).train.episodes == defaults["train"]["episodes"]
    assert config.load(None, [f"env.map={path}", "train.episodes=90"], algos.defaults("iql")).train.episodes == 90
    for text, named in [("algorithms:\n  iqll: {train: {episodes: 70}}\n", "unknown algorithm 'iqll'"),
                        ("algorithms:\n  iql: {train: {episode: 70}}\n", "train.episode"),
                        ("algorithms:\n  iql: 70\n", "algorithms.iql: expected a mapping"),
                        ("algorithms: [iql]\n", "algorithms: expected a mapping")]:
        (tmp_path / "office.settings.yaml").write_text(text)
        with pytest.raises(config.ConfigError, match=f"office.settings.yaml.*{named}"):
            config.load(None, [f"env.map={path}"], defaults)
    # a task name the map lacks: one line naming the map's tasks and the fix, before anything compiles
    (tmp_path / "office.settings.yaml").unlink()
    with pytest.raises(SystemExit) as e:
        main(["train", "hierarchical", "--map", path, "--set", "hierarchical.task_gamma={TRIAGE-BOTTOM-VICTIM: 0.9}",
              "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "TRIAGE-LEFT-VICTIM" in err and "hierarchical.task_gamma={}" in err


@pytest.mark.parametrize("name", ["two_rooms", "four_rooms", "office"])
@pytest.mark.parametrize("algo", ["hierarchical", "iql", "doc"])
def test_map_derived_defaults_give_the_committed_results_their_configs(name, algo):
    # four_rooms' and office's coordinator and chunking settings now come from their size, not their
    # settings files: the configs (hashes) of their committed results must be the ones a run gets today
    from jaxusar import algos, config

    committed = json.loads((Path(__file__).parents[1] / "results" / name / algo / "metrics.json").read_text())
    assert config.load(None, [f"env.map={name}"], algos.defaults(algo)).hash() == committed["config_hash"]


def test_map_derived_defaults_follow_the_team_and_the_map_size(tmp_path):
    from jaxusar import algos, config
    from jaxusar.envs import mapgen

    def write(name, **kw):
        _, text, regions = mapgen.generated_layout(name=name, seed=1, **kw)
        (tmp_path / f"{name}.txt").write_text(text)
        (tmp_path / f"{name}.regions.txt").write_text(regions)

    def coordinator(path, *sets):
        cfg = config.load(None, [f"env.map={path}", *sets], algos.defaults("hierarchical"))
        return cfg.hierarchical.coordinator, cfg

    for medics, kind, termination, episodes in [(2, "flat", "all", 100), (3, "factored", "all", 100),
                                                (4, "factored", "own", 300)]:
        write(f"m{medics}", height=12, width=16, rooms=4, medics=medics, victims=3)
        c, cfg = coordinator(tmp_path / f"m{medics}.txt")
        assert (c.kind, c.termination, c.episodes, c.eps_decay_steps) == (kind, termination, episodes, 2 * episodes)
        assert not cfg.dqn.one_hot_input and cfg.train.chunk_steps == 4000  # 192 cells: not a wide map
    # --set still wins over a derived default; a wide map looks its one-hot up, and chunks the paper's method
    c, _ = coordinator(tmp_path / "m4.txt", "hierarchical.coordinator.termination=all")
    assert c.termination == "all" and c.episodes == 300
    write("wide", height=20, width=30, rooms=6, medics=2, victims=3)
    _, cfg = coordinator(tmp_path / "wide.txt")
    assert cfg.dqn.one_hot_input and (cfg.train.chunk_steps, cfg.dqn.train_every) == (1000, 2)
    iql = config.load(None, [f"env.map={tmp_path / 'wide.txt'}"], algos.defaults("iql"))
    assert iql.dqn.one_hot_input and iql.dqn.train_every == config.DQNConfig().train_every  # chunking: hierarchical only
    # rubble: blocked agents dodge, and options run to their own end (three agents, not four) on five times
    # the budget and exploration
    c, _ = coordinator("two_rooms_rubble")
    assert (c.kind, c.termination, c.episodes, c.eps_decay_steps, c.dodge) == ("factored", "own", 500, 1000, True)
    # drawn victims: every learner tests on 8 draws; the coordinator learns longer over the draws, and
    # further ahead (its episodes run to the horizon)
    mini = config.load(None, ["env.map=minimap"], algos.defaults("hierarchical"))
    c = mini.hierarchical.coordinator
    assert (mini.train.test_draws, c.episodes, c.eps_decay_steps, c.test_every, c.gamma) == (8, 1500, 3000, 5, 0.99)
    assert config.load(None, ["env.map=two_rooms_rubble"], algos.defaults("hierarchical")).hierarchical.coordinator.gamma \
        == config.CoordinatorConfig().gamma
    iql = config.load(None, ["env.map=minimap"], algos.defaults("iql"))
    assert iql.train.test_draws == 8 and iql.train.episodes == 2000  # minimap's settings file: the baselines' budget
    assert config.load(None, ["env.map=two_rooms_rubble"], algos.defaults("iql")).train.test_draws == 1


def test_a_config_of_another_algorithm_says_how_to_start_from_it(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["train", "doc", "--config", str(Path(__file__).parents[1] / "configs" / "iql.yaml"), "--out", str(tmp_path / "x")])
    assert e.value.code == 2 and "--set algo=doc" in capsys.readouterr().err


FORK_LEARNER = '''"""Independent learners with Double DQN targets: a fork's learner, one file."""

import dataclasses

from jaxusar.core.learners import IndependentDQN, dqn_target
from jaxusar.envs import N_ACTIONS

ALGORITHM = "double_iql"
DEFAULTS = {"dqn": {"double_dqn": True}}


def make_learner(env, cfg):
    return IndependentDQN(env.obs_shape, N_ACTIONS, env.n_agents, cfg, dqn_target(cfg), obs_blocks=env.obs_blocks)
'''


def test_a_forks_learner_file_trains_from_the_cli(tmp_path):
    """docs/extending.md, 'Adding a learner': one file in a checkout's jaxusar/algos (an editable install imports the
    checkout, as PYTHONPATH does here) is listed by `jaxusar train --help` and trains."""
    import os
    import shutil
    import subprocess
    import sys

    checkout = tmp_path / "checkout"
    shutil.copytree(Path(__file__).parents[1] / "jaxusar", checkout / "jaxusar",
                    ignore=shutil.ignore_patterns("__pycache__"))
    (checkout / "jaxusar" / "algos" / "double_iql.py").write_text(FORK_LEARNER)
    env = {**os.environ, "PYTHONPATH": str(checkout)}

    def jaxusar(*argv):
        return subprocess.run([sys.executable, "-m", "jaxusar", *argv], cwd=checkout, env=env, capture_output=True,
                              text=True, timeout=600)

    listed = jaxusar("train", "--help")
    assert "double_iql" in listed.stdout and "Double DQN targets" in listed.stdout, listed.stderr
    run = jaxusar("train", "double_iql", "--trials", "1", "--out", str(tmp_path / "run"), "--quiet", *IQL_TINY)
    assert run.returncode == 0, run.stderr
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["algorithm"] == "double_iql" and m["config"]["dqn"]["double_dqn"] is True
    # a fork's file with a bug: one line naming the file, no traceback
    (checkout / "jaxusar" / "algos" / "double_iql.py").write_text(FORK_LEARNER + "\nundefined_name\n")
    broken = jaxusar("train", "double_iql", "--out", str(tmp_path / "x"))
    assert broken.returncode == 2 and "double_iql.py" in broken.stderr and "NameError" in broken.stderr
    assert "Traceback" not in broken.stderr


def test_an_unwritable_compile_cache_folder_is_a_warning(tmp_path):
    import jax

    from jaxusar.experiments.usage import enable_compile_cache

    before = jax.config.jax_compilation_cache_dir
    (tmp_path / "a_file").write_text("")
    with pytest.warns(UserWarning, match="cannot be written.*without the cache"):
        assert enable_compile_cache(folder=tmp_path / "a_file" / "xla") is None
    assert jax.config.jax_compilation_cache_dir == before  # untouched: the run goes on as before
    assert enable_compile_cache(enabled=False) is None


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_release_memory_hands_freed_heap_back_to_the_system():
    """Freed heap blocks between live ones stay resident under glibc until trimmed (what an XLA compile
    leaves behind); ``release_memory`` must return them, or a run's peak stacks on its garbage."""
    import ctypes

    from jaxusar.experiments import usage

    def rss_mb():
        return int(next(line for line in open("/proc/self/status") if line.startswith("VmRSS")).split()[1]) / 1024

    libc, size = ctypes.CDLL("libc.so.6"), 64 << 10  # below glibc's mmap threshold: from the heap
    libc.malloc.restype, libc.free.argtypes = ctypes.c_void_p, [ctypes.c_void_p]
    blocks = [libc.malloc(size) for _ in range(3000)]
    for b in blocks:
        ctypes.memset(b, 1, size)  # resident
    for b in blocks[::2]:
        libc.free(b)  # 94 MiB of holes between live blocks: glibc keeps them
    before = rss_mb()
    usage.release_memory()
    after = rss_mb()
    for b in blocks[1::2]:
        libc.free(b)
    assert before - after > 60, (before, after)


def test_a_second_run_loads_its_programs_and_a_corrupted_cache_is_a_warning(tmp_path):
    """The persistent compilation cache is on by default: the same command again compiles nothing; with
    every cache entry corrupted it warns, compiles again and gives the same numbers."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "cache")}
    out = tmp_path / "run"

    def run():
        done = subprocess.run([sys.executable, "-m", "jaxusar", "train", "iql", "--trials", "1", "--out", str(out),
                               "--force", "--quiet"] + IQL_TINY, env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr
        m = json.loads((out / "metrics.json").read_text())
        return m, done.stderr

    cold, _ = run()
    assert cold["usage"]["programs_compiled"] == cold["usage"]["programs"] > 0
    assert cold["usage"]["compile_cache"] == str(tmp_path / "cache") and cold["usage"]["peak_rss_mb"] > 0
    warm, _ = run()
    assert warm["usage"]["programs_loaded_from_cache"] == warm["usage"]["programs"] == cold["usage"]["programs"]
    assert warm["usage"]["programs_compiled"] == 0 and warm["episodes_to_optimal"] == cold["episodes_to_optimal"]
    for entry in (tmp_path / "cache").rglob("*"):
        if entry.is_file():
            entry.write_bytes(b"not an executable")
    again, err = run()
    assert "jaxusar: warning:" in err and "cache" in err and "Traceback" not in err
    assert again["usage"]["programs_compiled"] > 0 and again["best_test_return"] == cold["best_test_return"]


def test_figures_show_a_stopped_trials_kept_test_not_its_last_one():
    """A trial stops at the end of the chunk of its first optimal test (stop_at_optimal), so the last test
    it ran may be worse (here 300 steps after the 18-step one): the figures' curves continue with the kept
    params' test; a trial that ran every test is drawn as it ran."""
    nan = float("nan")
    curve = np.array([[300.0, 18.0, 300.0, nan, nan], [300.0, 250.0, 40.0, 30.0, 18.0]])
    np.testing.assert_array_equal(kept(curve, np.array([18.0, 18.0])),
                                  [[300, 18, 300, 18, 18], [300, 250, 40, 30, 18]])


def test_figures_stay_readable_on_big_maps(tmp_path):
    """Issue 39's figures: the sub-policy figure pages past 8 tasks (office: 23), several series drop the
    faint min-max bands that blurred together, the reward axis does not run down to the coordinator's
    invalid-option penalties, and a lower bound is labelled as one, not as 'optimal'."""
    import matplotlib.pyplot as plt

    from jaxusar.experiments import plots
    from jaxusar.experiments.hierarchical import PAGE_TASKS, subpolicy_pages

    rng = np.random.default_rng(0)
    n = PAGE_TASKS + 1
    sub = {"train_length": rng.uniform(10, 300, (n, 2, 40)), "test_length": rng.uniform(10, 300, (n, 2, 4)),
           "test_coverage": rng.uniform(0, 1, (n, 2, 4)), "best_length": np.full((n, 2), 12.0),
           "best_coverage": np.ones((n, 2)), "test_episode": np.arange(10, 50, 10)}
    pages = subpolicy_pages(sub, [f"task{k}" for k in range(n)], tmp_path, 300, np.full(n, -1))
    assert [p.name for p in pages] == ["fig4_subpolicies.png", "fig4_subpolicies_2.png"]

    def result(low):
        returns = rng.uniform(0, 200, (2, 40))
        returns[:, :5] = low  # the coordinator's first episodes: invalid options, -100 each
        return {"train_length": rng.uniform(10, 300, (2, 40)), "train_return": returns,
                "test_episode": np.arange(10, 50, 10), "test_length": rng.uniform(10, 300, (2, 4)),
                "test_return": rng.uniform(0, 200, (2, 4)), "best_length": np.full(2, 42.0),
                "best_return": np.full(2, 200.0)}

    drawn = {}
    close = plt.close
    try:
        plt.close = lambda fig: drawn.setdefault("fig", fig)  # keep the figure to look at its axes
        plots.training_figure([("2 options", result(0.0)), ("4 options", result(0.0))], tmp_path / "k.png", "K",
                              horizon=300, optimal_steps=42, reward_range=(0.0, 200.0), reference="lower bound")
        fig = drawn.pop("fig")
        assert len(fig.axes[0].collections) == 2  # one interquartile band per series, no min-max bands
        labels = [t.get_text() for t in fig.legends[0].get_texts()]
        assert "lower bound (42 steps)" in labels and "2 options" in labels and not fig.axes[0].get_legend()
        plots.training_figure(result(-30_000.0), tmp_path / "c.png", "coordinator", horizon=300, optimal_steps=18,
                              smooth_window=1, reward_range=(0.0, 200.0))
        fig = drawn.pop("fig")
        assert fig.axes[1].get_ylim()[0] == pytest.approx(-10.0)  # not -30,000
        assert any("cut off below" in t.get_text() for t in fig.axes[1].texts)
        assert "optimal (18 steps)" in [t.get_text() for t in fig.legends[0].get_texts()]
    finally:
        plt.close = close
        plt.close("all")
