"""Ablation of the shared DQN core on the paper's method, on tuning seeds (the reported runs use seed 0).

Two parts of the method are tuned separately, each with the measure that predicts the team:

* ``subpolicies``: trains every sub-policy (all tasks x trials, the first stage of ``jaxusar train
  hierarchical``) and reports per task the episodes to optimal from every initiation state, the paper's
  single-start episodes to optimal, and the kept params' coverage (the fraction of initiation states
  from which the greedy policy is optimal), plus wall seconds and env steps per lane.
* ``coordinator``: trains the coordinator over exact sub-policies (the planner's distance tables), so
  its own learning is measured apart from the sub-policies' errors; reports trials optimal and the median
  episodes to optimal within 100 episodes.

The baselines are tuned the same way, on their own measure (``iql``, ``doc``: a full ``jaxusar train``
of that algorithm into a scratch folder): trials optimal, trials solved at any length, the median
episodes to either, and the best test's steps per trial (per K for option-critic).

Settings are ``--set`` overrides on the defaults of ``jaxusar train hierarchical`` (``dqn.*``,
``hierarchical.*``) or of the coordinator (``reward_scale=0.01 gradient_steps=8``: CoordinatorConfig keys)::

    python benchmarks/ablation.py subpolicies --seed 1000 --trials 8 --set dqn.n_step=1
    python benchmarks/ablation.py coordinator --seed 1000 --trials 16 --set gradient_steps=1
    python benchmarks/ablation.py iql --seed 1000 --set dqn.n_step=3
    python benchmarks/ablation.py doc --seed 1000 --set doc.options=[2] --set dqn.tau=0.005

Each run appends its numbers to ``benchmarks/results/ablation.jsonl`` with the settings and the CPU.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
import yaml

from jaxusar import algos, config
from jaxusar.experiments import hierarchical, train
from jaxusar.experiments.stats import summarize
from jaxusar.experiments.train import cpu_name, print_progress

ROOT = Path(__file__).resolve().parents[1]


def subpolicies(seed: int, trials: int, sets: list[str]) -> dict:
    cfg = config.load(None, sets + [f"seed={seed}"], defaults=algos.defaults("hierarchical"))
    exp = hierarchical.Experiment(cfg, jax.random.split(jax.random.PRNGKey(seed), trials))
    stage = exp.chains[0][0]
    start = time.perf_counter()
    state = stage.trainer.train(stage.keys, env_params=stage.env_params,
                                progress=lambda info: print_progress(stage.name, info))
    r = stage.trainer.results(jax.block_until_ready(state))
    wall = time.perf_counter() - start
    names = [t.name for t in exp.b["tasks"]]
    def lanes(xs):  # per lane, None (never) as nan, shaped [trial, task]
        return np.array([np.nan if x is None else x for x in xs], float).reshape(trials, len(names))

    eto, start_eto = lanes(r["episodes_to_optimal"]), lanes(r["episodes_to_start_optimal"])
    cov = np.asarray(r["best_coverage"]).reshape(trials, len(names))
    sums = np.where(np.isnan(eto).any(1), np.nan, np.nansum(eto, 1))
    def med(x):  # the median with never as +inf; None when it is never
        return None if np.isnan(x).sum() * 2 >= len(x) else float(np.median(np.where(np.isnan(x), np.inf, x)))

    return {
        "per_task": {n: {"trials_optimal": int((~np.isnan(eto[:, k])).sum()), "median": med(eto[:, k]),
                         "start_trials_optimal": int((~np.isnan(start_eto[:, k])).sum()),
                         "start_median": med(start_eto[:, k]),
                         "coverage_worst": float(cov[:, k].min()), "coverage_mean": float(cov[:, k].mean()),
                         "episodes_to_optimal": [None if np.isnan(e) else int(e) for e in eto[:, k]]}
                     for k, n in enumerate(names)},
        "trials_all_optimal": int((~np.isnan(sums)).sum()), "sum_median": med(sums),
        "coverage_worst": float(cov.min()), "wall_seconds": round(wall, 1),
        "env_steps_per_lane": float(np.mean(r["env_steps"])),
    }


def coordinator(seed: int, trials: int, sets: list[str]) -> dict:
    sys.path.insert(0, str(ROOT))
    from tests.test_hierarchical import _oracle_coordinator  # the exact sub-policies the tests use

    overrides = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in sets)}
    start = time.perf_counter()
    res = _oracle_coordinator(episodes=100, trials=trials, seed=seed, **overrides)[3]
    eto = res["episodes_to_optimal"]
    x = np.array([np.inf if e is None else e for e in eto])
    return {"trials_optimal": int(np.isfinite(x).sum()), "median": float(np.median(x)), "episodes_to_optimal": eto,
            "wall_seconds": round(time.perf_counter() - start, 1)}


def baseline(algo: str, seed: int, trials: int, sets: list[str]) -> dict:
    cfg = config.load(None, sets + [f"seed={seed}"], defaults=algos.defaults(algo))
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as out:
        m = train.run(cfg, trials, out, quiet=True)
    wall = round(time.perf_counter() - start, 1)
    def row(m):
        solved = m["episodes_to_solved"]
        return {"trials_optimal": sum(e is not None for e in m["episodes_to_optimal"]), "median": m["median"],
                "trials_solved": sum(e is not None for e in solved), "solved_median": summarize(solved)["median"],
                "best_test_return": m["best_test_return"], "best_test_steps": m["best_test_steps"]}
    per = {f"K{k}": row(v) for k, v in m["per_options"].items()} if "per_options" in m else row(m)
    return {**per, "wall_seconds": wall}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("part", choices=["subpolicies", "coordinator", "iql", "doc"])
    ap.add_argument("--seed", type=int, default=1000, help="a tuning seed (the reported runs use 0)")
    ap.add_argument("--trials", type=int, default=8)
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--out", default=str(ROOT / "benchmarks/results/ablation.jsonl"))
    args = ap.parse_args(argv)
    if args.seed == 0:
        ap.error("--seed 0 is the reported runs' seed; tune on others (e.g. 1000)")
    if args.part in ("iql", "doc"):
        numbers = baseline(args.part, args.seed, args.trials, args.sets)
    else:
        numbers = (subpolicies if args.part == "subpolicies" else coordinator)(args.seed, args.trials, args.sets)
    row = {"part": args.part, "sets": args.sets, "seed": args.seed, "trials": args.trials, **numbers,
           "machine": cpu_name(), "jax": jax.__version__}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "a") as f:
        f.write(json.dumps(row) + "\n")
    print(json.dumps(row, indent=1))


if __name__ == "__main__":
    main()
