"""Option-critic's experiment (paper Sec. V, Fig. 5): one Trainer per number of options K, all K on one figure.

K changes the networks' shapes, so each K is its own jitted, vmapped call over the trials (the same
trial keys for every K): one chain each, which the runner trains side by side (one per CPU core; on
CPU one such call keeps one core busy, DESIGN.md), largest K first; the numbers are the same as
running them one after another. Output folder::

    metrics.json      summary: per K episodes_to_optimal, best, median, fraction_optimal,
                      episodes_to_solved, compile and run seconds; the total wall time
    fig5_doc.png      train and test steps and rewards vs episodes, the K on the same axes (Fig. 5)
    K{K}/metrics.json what a flat learner's metrics.json holds, plus ``options``: K
    K{K}/curves.csv, K{K}/params/trial_N.msgpack

Each K's seconds are its own, overlapping the other K's when they run side by side.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax

from jaxusar import envs, planning
from jaxusar.algos import option_critic
from jaxusar.config import ConfigError, ExperimentConfig
from jaxusar.core import Trainer
from jaxusar.experiments.plots import reward_range, training_figure
from jaxusar.experiments.runner import Stage
from jaxusar.experiments.stats import in_words
from jaxusar.experiments.train import environment_info, flat_metrics, write_trial_files


class Experiment:
    """One chain per K (their networks differ in shape), the same trial keys for every K, largest K first."""

    FIGURES = ("fig5_doc.png",)

    def __init__(self, cfg: ExperimentConfig, keys: jax.Array, options: tuple[int, ...] | None = None):
        ks = tuple(int(k) for k in (options or cfg.doc.options))
        if not ks or any(k < 1 for k in ks) or len(set(ks)) != len(ks):
            raise ConfigError(f"options {ks}: distinct numbers of options, each >= 1")
        self.ks = ks
        self.cfg = cfg = dataclasses.replace(cfg, doc=dataclasses.replace(cfg.doc, options=ks))  # what ran
        self.env = envs.make(cfg.env.map, **cfg.env.overrides())
        self.reference = planning.team_reference(self.env)
        self.optimal = self.reference["steps"]
        self.chains = []
        for k in sorted(ks, reverse=True):  # the longest first
            learner = option_critic.make_learner(self.env, cfg.dqn, cfg.doc, options=k)
            trainer = Trainer(self.env, learner, cfg.train, learning_starts=cfg.dqn.learning_starts,
                              train_every=cfg.dqn.train_every, gradient_steps=cfg.dqn.gradient_steps,
                              optimal_steps=self.optimal)
            self.chains.append([Stage(f"doc/K{k}", trainer, keys)])

    def finish(self, out: Path, outcomes: dict, figures: bool = True) -> dict:
        cfg, ks = self.cfg, self.ks
        per_k = {}
        for k in ks:
            o = outcomes[f"doc/K{k}"]
            k_out = out / f"K{k}"
            k_out.mkdir(exist_ok=True)
            per_k[k] = flat_metrics(cfg, o.results, self.reference, o, options=k)
            write_trial_files(k_out, o.results)
            (k_out / "metrics.json").write_text(json.dumps(per_k[k], indent=2))
            m = per_k[k]
            print(f"[doc K={k}] {in_words(m['episodes_to_optimal'], cfg.train.episodes)}; task solved (any "
                  f"length) in {sum(e is not None for e in m['episodes_to_solved'])} of {m['trials']}", flush=True)
        series = [(f"{k} options", outcomes[f"doc/K{k}"].results) for k in ks]
        if figures:
            training_figure(series, out / "fig5_doc.png", f"simplified distributed option-critic on {cfg.env.map}",
                            horizon=self.env.horizon, optimal_steps=self.optimal, reward_range=reward_range(self.env),
                            reference=self.reference["reference"])
        keep = ("episodes_to_optimal", "best", "median", "iqm", "iqm_ci95", "fraction_optimal", "episodes_to_solved",
                "best_test_return", "best_test_steps", "optimality_gap", "env_steps", "seconds")
        return {
            "algorithm": cfg.algo, "trials": per_k[ks[0]]["trials"], "options": list(ks),
            **{k: v for k, v in per_k[ks[0]].items() if k in ("optimal_team_steps", "reference", "team_lower_bound")},
            "optimal_slack": cfg.train.optimal_slack,
            "per_options": {str(k): {key: per_k[k][key] for key in keep} for k in ks},
            "config": cfg.to_dict(), "config_hash": cfg.hash(), "environment": environment_info(),
        }
