"""Option-critic's experiment (paper Sec. V, Fig. 5): one Trainer per number of options K, all K on one figure.

K changes the networks' shapes, so each K is its own jitted, vmapped call over the trials (the same
trial keys for every K). On CPU one such call keeps one core busy (its cost is FLOPs, DESIGN.md), so
up to ``workers`` K run side by side in threads (XLA releases the GIL), largest K first; the numbers
are the same as running them one after another. Output folder::

    metrics.json      summary: per K episodes_to_optimal, best, median, fraction_optimal,
                      episodes_to_solved, wall_seconds; the total wall time
    fig5_doc.png      train and test steps and rewards vs episodes, the K on the same axes (Fig. 5)
    K{K}/metrics.json the keys experiments.train.run_flat writes, plus ``options``: K
    K{K}/curves.csv, K{K}/params/trial_N.msgpack   as run_flat writes them

Each K's wall_seconds is its own elapsed time, overlapping the other K's when they run side by side.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax

from jaxusar import envs, planning
from jaxusar.algos import option_critic
from jaxusar.config import ConfigError, ExperimentConfig
from jaxusar.core import Trainer
from jaxusar.experiments.plots import training_figure
from jaxusar.experiments.train import (
    environment_info, flat_metrics, prepare_out, print_progress, write_trial_files,
)


def run(cfg: ExperimentConfig, trials: int, out: str | Path, force: bool = False, quiet: bool = False,
        options: tuple[int, ...] | None = None, workers: int | None = None) -> dict:
    """Train ``trials`` seeds of DOC for each K in ``options`` (default ``cfg.doc.options``); write ``out``.

    ``workers``: how many K train at once (default: one per CPU core, at most one per K).
    """
    if trials < 1:
        raise ConfigError(f"--trials must be >= 1, got {trials}")
    ks = tuple(int(k) for k in (options or cfg.doc.options))
    if not ks or any(k < 1 for k in ks) or len(set(ks)) != len(ks):
        raise ConfigError(f"options {ks}: distinct numbers of options, each >= 1")
    cfg = dataclasses.replace(cfg, doc=dataclasses.replace(cfg.doc, options=ks))  # record what ran
    out = prepare_out(out, force)
    k_outs = {k: prepare_out(out / f"K{k}", force) for k in ks}
    start_all = time.perf_counter()
    env = envs.make(cfg.env.map, **cfg.env.overrides())
    optimal = planning.optimal_team_steps(env)
    keys = jax.random.split(jax.random.PRNGKey(cfg.seed), trials)

    workers = max(1, min(len(ks), workers or os.cpu_count() or 1))

    def train_k(k: int) -> dict:
        """Train K's trials and write K{K}/ as soon as they finish (side by side with other K)."""
        start = time.perf_counter()
        learner = option_critic.make_learner(env, cfg.dqn, cfg.doc, options=k)
        trainer = Trainer(env, learner, cfg.train, learning_starts=cfg.dqn.learning_starts,
                          train_every=cfg.dqn.train_every, optimal_steps=optimal)
        state = trainer.train(keys, progress=None if quiet else print_progress(f"doc K={k}"))
        results = trainer.results(state)
        wall = time.perf_counter() - start
        eto = results["episodes_to_optimal"]
        metrics = {**flat_metrics(cfg, trials, results, optimal, wall, options=k), "concurrent_runs": workers}
        write_trial_files(k_outs[k], results)
        (k_outs[k] / "metrics.json").write_text(json.dumps(metrics, indent=2))
        if not quiet:
            print(f"[doc K={k}] episodes_to_optimal per trial: {eto}; best {metrics['best']}, "
                  f"median {metrics['median']}, {metrics['fraction_optimal']:.0%} optimal; "
                  f"first test triaging every victim after: {metrics['episodes_to_solved']}; {wall:.1f}s", flush=True)
        return {"metrics": metrics, "results": results}

    with ThreadPoolExecutor(workers) as pool:
        futures = {k: pool.submit(train_k, k) for k in sorted(ks, reverse=True)}  # longest first
        per_k = {k: futures[k].result() for k in ks}
    series = [(f"{k} options", per_k[k]["results"]) for k in ks]
    training_figure(series, out / "fig5_doc.png", f"simplified distributed option-critic on {cfg.env.map}",
                    horizon=env.horizon, optimal_steps=optimal)
    wall_all = time.perf_counter() - start_all
    keep = ("episodes_to_optimal", "best", "median", "fraction_optimal", "episodes_to_solved",
            "best_test_return", "best_test_steps", "env_steps_per_trial", "wall_seconds")
    summary = {
        "algorithm": cfg.algo, "trials": trials, "options": list(ks), "optimal_team_steps": optimal,
        "optimal_slack": cfg.train.optimal_slack,
        "per_options": {str(k): {key: per_k[k]["metrics"][key] for key in keep} for k in ks},
        "wall_seconds": round(wall_all, 2), "concurrent_runs": workers,
        "config": cfg.to_dict(), "config_hash": cfg.hash(), "environment": environment_info(),
    }
    (out / "metrics.json").write_text(json.dumps(summary, indent=2))
    if not quiet:
        bests = ", ".join(f"K={k}: best {per_k[k]['metrics']['best']}" for k in ks)
        print(f"[doc] {bests}; {wall_all:.1f}s in all; wrote {out}", flush=True)
    return {"metrics": summary, "per_options": per_k}
