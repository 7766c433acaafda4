"""Run one algorithm's N trials and write its results folder (side effects live here, not in core).

Output folder::

    metrics.json        algorithm, trials, episodes_to_optimal (list over trials, null = never),
                        summary statistics, wall_seconds (compile included), resolved config, versions
    curves.csv          trial, kind (train|test), episode, return, steps, optimal
    params/trial_K.msgpack   best test params of trial K (flax.serialization)
    curves.png          train and test steps and rewards vs episodes, band over trials (paper Fig. 6 style)
"""

from __future__ import annotations

import csv
import importlib
import json
import platform
import time
from pathlib import Path
from typing import Callable

import flax
import jax
import numpy as np
import optax
from flax import serialization

from jaxusar import envs, planning
from jaxusar.config import ConfigError, ExperimentConfig
from jaxusar.core import Trainer
from jaxusar.experiments.plots import training_figure


ALIASES = {"doc": "option_critic", "hierarchical": "coordinator"}  # command-line name -> module in jaxusar/algos


def algorithm_module(name: str):
    """``jaxusar.algos.<name>``: adding a learner = adding one file there."""
    try:
        return importlib.import_module(f"jaxusar.algos.{ALIASES.get(name, name)}")
    except ModuleNotFoundError:
        import pkgutil

        import jaxusar.algos as algos

        known = sorted({m.name for m in pkgutil.iter_modules(algos.__path__)} | set(ALIASES))
        raise ConfigError(f"unknown algorithm {name!r}; available: {', '.join(known)}") from None


def environment_info() -> dict:
    return {"jax": jax.__version__, "flax": flax.__version__, "optax": optax.__version__,
            "numpy": np.__version__, "python": platform.python_version(), "machine": platform.machine(),
            "processor": cpu_name(), "devices": [str(d) for d in jax.devices()]}


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def summarize(episodes_to_optimal: list) -> dict:
    """best, median (nulls count as never: median is null if half or more never got there), fraction."""
    reached = sorted(e for e in episodes_to_optimal if e is not None)
    n = len(episodes_to_optimal)
    padded = reached + [np.inf] * (n - len(reached))
    median = float(np.median(padded)) if n else None
    return {"best": reached[0] if reached else None,
            "median": None if median is None or not np.isfinite(median) else median,
            "fraction_optimal": len(reached) / n if n else 0.0}


def print_progress(name: str) -> Callable[[dict], None]:
    def show(p):
        print(f"[{name}] chunk {p['chunk']}: episodes {p['episodes_min']}/{p['episodes_total']} "
              f"(mean {p['episodes_mean']:.0f}), {p['elapsed']:.1f}s elapsed, ETA {p['eta']:.0f}s", flush=True)
    return show


def build(cfg: ExperimentConfig):
    """env, planner optimum, learner, trainer for a flat (non-hierarchical) algorithm."""
    env = envs.make(cfg.env.map, **cfg.env.overrides())
    optimal = planning.optimal_team_steps(env)
    learner = algorithm_module(cfg.algo).make_learner(env, cfg.dqn)
    trainer = Trainer(env, learner, cfg.train, learning_starts=cfg.dqn.learning_starts,
                      train_every=cfg.dqn.train_every, optimal_steps=optimal)
    return env, optimal, learner, trainer


def write_curves_csv(path: Path, results: dict) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["trial", "kind", "episode", "return", "steps", "optimal"])
        for k in range(results["train_return"].shape[0]):
            for i, (r, s) in enumerate(zip(results["train_return"][k], results["train_length"][k])):
                w.writerow([k, "train", i + 1, float(r), int(s), ""])
            for e, r, s, o in zip(results["test_episode"], results["test_return"][k], results["test_length"][k],
                                  results["test_optimal"][k]):
                w.writerow([k, "test", int(e), float(r), int(s), int(o)])


def save_params(folder: Path, best_params) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    n = jax.tree.leaves(best_params)[0].shape[0]
    for k in range(n):
        trial = jax.tree.map(lambda x: np.asarray(x[k]), best_params)
        (folder / f"trial_{k}.msgpack").write_bytes(serialization.to_bytes(trial))


def prepare_out(out: str | Path, force: bool) -> Path:
    out = Path(out)
    if (out / "metrics.json").exists() and not force:
        raise FileExistsError(f"{out}/metrics.json exists: a finished run is never overwritten; pass --force")
    out.mkdir(parents=True, exist_ok=True)
    return out


def run(cfg: ExperimentConfig, trials: int, out: str | Path, force: bool = False, quiet: bool = False,
        **extra) -> dict:
    """Train ``trials`` seeds of ``cfg.algo`` and write the results folder.

    Algorithms whose experiment is more than one Trainer (the hierarchical method, option-critic's
    several K) have a runner in ``jaxusar/experiments/<algo>.py`` with this same signature.
    """
    try:
        runner = importlib.import_module(f"jaxusar.experiments.{cfg.algo}")
    except ModuleNotFoundError:
        return run_flat(cfg, trials, out, force=force, quiet=quiet)
    return runner.run(cfg, trials, out, force=force, quiet=quiet, **extra)


def flat_metrics(cfg: ExperimentConfig, trials: int, results: dict, optimal: int, wall: float, **extra) -> dict:
    """metrics.json of one Trainer's results (``extra`` keys go after ``algorithm``)."""
    eto = results["episodes_to_optimal"]
    return {
        "algorithm": cfg.algo, **extra, "trials": trials, "episodes_to_optimal": eto, **summarize(eto),
        "episodes_to_solved": results["episodes_to_solved"],
        "optimal_team_steps": optimal, "optimal_slack": cfg.train.optimal_slack,
        "best_test_return": results["best_return"].tolist(), "best_test_steps": results["best_length"].tolist(),
        "env_steps_per_trial": results["env_steps"].tolist(), "wall_seconds": round(wall, 2),
        "config": cfg.to_dict(), "config_hash": cfg.hash(), "environment": environment_info(),
    }


def write_trial_files(out: Path, results: dict) -> None:
    """curves.csv and params/ of one Trainer's results."""
    write_curves_csv(out / "curves.csv", results)
    save_params(out / "params", results["best_params"])


def run_flat(cfg: ExperimentConfig, trials: int, out: str | Path, force: bool = False, quiet: bool = False) -> dict:
    """Train ``trials`` seeds of a flat algorithm in one vmapped call and write the results folder."""
    if trials < 1:
        raise ConfigError(f"--trials must be >= 1, got {trials}")
    out = prepare_out(out, force)
    start = time.perf_counter()
    env, optimal, _, trainer = build(cfg)
    keys = jax.random.split(jax.random.PRNGKey(cfg.seed), trials)
    state = trainer.train(keys, progress=None if quiet else print_progress(cfg.algo))
    results = trainer.results(state)
    wall = time.perf_counter() - start
    eto = results["episodes_to_optimal"]
    metrics = flat_metrics(cfg, trials, results, optimal, wall)
    write_trial_files(out, results)
    training_figure(results, out / "curves.png", f"{cfg.algo} on {cfg.env.map}", horizon=env.horizon,
                    optimal_steps=optimal)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    if not quiet:
        print(f"[{cfg.algo}] episodes_to_optimal per trial: {eto}; best {metrics['best']}, "
              f"median {metrics['median']}, {metrics['fraction_optimal']:.0%} optimal; {wall:.1f}s; wrote {out}")
    return {"metrics": metrics, "results": results}
