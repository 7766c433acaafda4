"""Ablation of the shared DQN core on the paper's method: which sample-efficiency settings earn their place.

Each named setting is a list of ``--set`` overrides on top of ``jaxusar train hierarchical``'s defaults
(the ladder below adds one change at a time, from the settings before this ablation to today's
defaults, then tries alternatives beside them). Every setting trains the sub-policies and the coordinator
on the same tuning seed (default 1000: disjoint from the reported runs, which use seed 0) and reports:
sub-policy lanes (trials x tasks) optimal from every initiation state, the worst kept sub-policy's
coverage, the coordinator's and the end-to-end trials optimal, median episodes, and wall seconds
(compilation included; run them one at a time on a quiet machine for times to compare).

    python benchmarks/ablation.py                      # every setting, seed 1000, 8 trials
    python benchmarks/ablation.py --only defaults "n_step 1" --trials 8 --seed 1000
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from jaxusar import config
from jaxusar.algos import coordinator as coord
from jaxusar.experiments import train

BEFORE = ["hierarchical.subpolicy_features=factored", "hierarchical.navigate_start=mixed", "dqn.reward_scale=1.0",
          "dqn.n_step=1", "dqn.train_every=4", "dqn.gradient_steps=1", "dqn.lr=0.0005", "dqn.lr_schedule=constant",
          "hierarchical.coordinator.reward_scale=1.0", "hierarchical.coordinator.n_step=1",
          "hierarchical.coordinator.gradient_steps=1"]

SETTINGS = {
    "before (previous defaults)": BEFORE,
    "defaults": [],
}


def run_setting(sets: list[str], seed: int, trials: int) -> dict:
    cfg = config.load(None, sets + [f"seed={seed}"], defaults={"algo": "hierarchical", **coord.DEFAULTS})
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        m = train.run(cfg, trials, Path(out) / "run", quiet=True)
        wall = time.perf_counter() - start
    per_task = m["subpolicy_episodes_to_optimal"]["per_task"]
    lanes = [e for eto in per_task.values() for e in eto]
    cov = [c for cs in m["subpolicy_coverage"].values() for c in cs]
    sums = m["subpolicy_episodes_to_optimal"]["sum"]
    med = lambda xs: None if sum(x is None for x in xs) * 2 >= len(xs) else float(np.median(
        [np.inf if x is None else x for x in xs]))
    return {"sets": sets, "seed": seed, "trials": trials, "wall_seconds": round(wall, 1),
            "subpolicy_lanes_optimal": sum(e is not None for e in lanes), "subpolicy_lanes": len(lanes),
            "worst_coverage": min(cov), "mean_coverage": float(np.mean(cov)),
            "subpolicy_sum_median": med(sums),
            "coordinator_optimal": sum(e is not None for e in m["coordinator_episodes_to_optimal"]),
            "coordinator_median": med(m["coordinator_episodes_to_optimal"]),
            "end_to_end_optimal": sum(e is not None for e in m["episodes_to_optimal"]),
            "end_to_end_median": med(m["episodes_to_optimal"]),
            "episodes_to_optimal": m["episodes_to_optimal"]}


def table(rows: dict) -> str:
    show = lambda x: "never" if x is None else f"{x:,.0f}"  # noqa: E731
    lines = ["| setting | sub-policies optimal everywhere (lanes) | kept coverage: worst / mean | median sub-policy "
             "sum | coordinator optimal, median | end to end optimal, median | wall s |",
             "|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        t = r["trials"]
        lines.append(f"| {name} | {r['subpolicy_lanes_optimal']}/{r['subpolicy_lanes']} | {r['worst_coverage']:.1%} / "
                     f"{r['mean_coverage']:.1%} | {show(r['subpolicy_sum_median'])} | {r['coordinator_optimal']}/{t}, "
                     f"{show(r['coordinator_median'])} | {r['end_to_end_optimal']}/{t}, {show(r['end_to_end_median'])} "
                     f"| {r['wall_seconds']:.0f} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1000, help="tuning seed (the reported runs use 0)")
    ap.add_argument("--trials", type=int, default=8)
    ap.add_argument("--only", nargs="*", help="names of settings to run (default: all)")
    ap.add_argument("--out", default="benchmarks/results/ablation.json", help="JSON file, merged by setting name")
    args = ap.parse_args(argv)
    names = args.only or list(SETTINGS)
    unknown = [n for n in names if n not in SETTINGS]
    if unknown:
        ap.error(f"unknown setting(s) {unknown}; known: {list(SETTINGS)}")
    for n in names:  # every setting is checked before any trains
        config.load(None, SETTINGS[n], defaults={"algo": "hierarchical", **coord.DEFAULTS})
    out = Path(args.out)
    rows = json.loads(out.read_text()) if out.exists() else {}
    for n in names:
        rows[n] = run_setting(SETTINGS[n], args.seed, args.trials)
        rows[n]["machine"] = train.cpu_name()
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(rows, indent=2))
        print(f"{n}: {json.dumps({k: v for k, v in rows[n].items() if k != 'sets'})}", flush=True)
    print(table({n: rows[n] for n in SETTINGS if n in rows}))


if __name__ == "__main__":
    main()
