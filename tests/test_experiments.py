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
    (["train", "iql", "--options", "2,4"], "--options"),
    (["train", "doc", "--options", "2,x"], "--options"),
    (["train", "iql", "--config", "/nonexistent.yaml"], "does not exist"),
    (["train", "iql", "--set", "dqn.n_step_cut_exploring=true", "--set", "dqn.n_step_cut_greedy=true"],
     "n_step_cut_greedy"),
])
def test_train_bad_input_is_one_line_before_compiling(argv, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv + ["--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and message in err and "Traceback" not in err
    assert not (tmp_path / "x" / "metrics.json").exists()


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
    """What `jaxusar train --help` lists trains on a tiny budget: iql above, doc in
    tests/test_option_critic.py (test_runner_learns_to_triage_on_a_tiny_map_and_writes_results), and the
    paper's method here, with its default config (and with goal-conditioned navigation), on a map without
    the two-rooms map's task names."""
    from jaxusar import algos

    assert sorted(algos.registry()) == ["doc", "hierarchical", "iql"]
    assert algos.registry()["hierarchical"].__name__ == "jaxusar.algos.coordinator"
    out = tmp_path / "hierarchical"
    assert main(["train", "hierarchical", "--trials", "1", "--out", str(out), "--quiet",
                 "--map", write_office(tmp_path)]
                + sets("train.episodes=20", "train.test_every=10", "train.chunk_steps=2000",
                       "hierarchical.coordinator.episodes=4", "hierarchical.coordinator.chunk_steps=4",
                       f"hierarchical.navigation={navigation}")) == 0
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
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("name", ["options", "subpolicies", "coordinator", "option_critic"])
def test_modules_that_are_parts_of_an_algorithm_are_not_trainable(name, capsys):
    with pytest.raises(SystemExit) as e:
        main(["train", name])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "unknown algorithm" in err and "doc, hierarchical, iql" in err


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
    return IndependentDQN(env.obs_dim, N_ACTIONS, env.n_agents, cfg, dqn_target(cfg), obs_blocks=env.obs_blocks)
'''


def test_a_forks_learner_file_trains_from_the_cli(tmp_path):
    """README 'Adding a learner': one file in a checkout's jaxusar/algos (an editable install imports the
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
