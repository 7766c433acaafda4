"""The flat (paper) and factored coordinators side by side, over exact sub-policies (or a run's trained ones).

Exact sub-policies (``subpolicies.exact_subpolicies``: shortest-path actions from the planner's
distance tables) isolate the coordinator: each map's default coordinator settings, 8 trials
(``--seed``), both kinds on the same keys, one after the other in one process. Reported per map and
kind: trials whose greedy team test triaged every victim, trials that reached the reference (the exact
optimum, or the lower bound where the joint search is out of reach), the median best team test as a
ratio to the lower bound, the network's parameters, and compile + run seconds; on a map whose victims are
drawn, each trial's kept coordinator judged on the fixed draws (``scripted.judge``: normalized score,
draws with every victim saved, critical victims saved).

With ``--subpolicies RUN`` the coordinators run over a hierarchical run's trained sub-policies instead
(RUN: the folder with its metrics.json and params/, e.g. results/minimap/hierarchical): its config is
the base, under the map's derived defaults, its settings file and ``--set``, so coordinator variants can
be compared over the same trained sub-policies without training them again. With the run's seed and
trials, at the defaults that made it, this repeats the run's own coordinator stage (the same keys).

    python benchmarks/coordinators.py            # writes benchmarks/results/coordinators.json
    python benchmarks/coordinators.py --maps office --kinds factored \
        --set hierarchical.coordinator.block_patience=2 --out /tmp/office.json   # one variant, one map
    python benchmarks/coordinators.py --maps minimap --kinds factored --seed 1000 \
        --subpolicies runs/minimap-1000 --set hierarchical.coordinator.n_step=1   # over trained sub-policies
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from coordinator_cost import load_subpolicies
from jaxusar import algos, config
from jaxusar.algos import coordinator as coord
from jaxusar.algos import subpolicies as sp
from jaxusar.experiments import hierarchical
from jaxusar.experiments import scripted as sc
from jaxusar.experiments.train import environment_info, greedy_episodes

MAPS = ("two_rooms", "three_rooms", "four_rooms", "office")


def trained(folder: Path, trials: int) -> tuple[dict, dict]:
    """A hierarchical run folder's metrics and its first ``trials`` trials' kept sub-policy params, stacked
    [trial, task, ...] (``coordinator_cost.load_subpolicies``)."""
    meta = folder / "metrics.json"
    if not meta.is_file():
        raise SystemExit(f"--subpolicies {folder}: no {meta} (a finished hierarchical run's folder)")
    metrics = json.loads(meta.read_text())
    if metrics.get("algorithm") != "hierarchical":
        raise SystemExit(f"--subpolicies {folder}: a run of {metrics.get('algorithm')!r}, not of hierarchical")
    return metrics, load_subpolicies(folder, trials)


def run(map_name: str, kind: str, trials: int, seed: int, overrides: tuple[str, ...] = (),
        subpolicies: tuple[dict, dict] | None = None) -> dict:
    """One map and coordinator kind over exact sub-policies, or over ``subpolicies`` (``trained``)."""
    base = algos.defaults("hierarchical") if subpolicies is None else subpolicies[0]["config"]
    cfg = config.load(None, [f"env.map={map_name}", f"hierarchical.coordinator.kind={kind}", f"seed={seed}",
                             *overrides], defaults=base)
    keys = jax.random.split(jax.random.PRNGKey(seed), trials)
    b = hierarchical.build(cfg)
    if subpolicies is None:
        tables = sp.exact_subpolicies(b["subtask_env"], b["task_params"])
        params = coord.CoordinatorParams(subpolicy=jnp.broadcast_to(tables, (trials, *tables.shape)))
    else:
        if [t.name for t in b["tasks"]] != subpolicies[0]["tasks"]:
            raise SystemExit(f"--subpolicies: its run's sub-tasks are not those of {map_name} with these settings")
        params = b["coordinator_params"](subpolicies[1])
    trainer = b["coord_trainer"]
    t = time.perf_counter()
    res = trainer.results(trainer.train(keys, env_params=params))
    seconds = time.perf_counter() - t
    bound = b["reference"]["lower_bound"]
    solved = [e is not None for e in res["episodes_to_solved"]]
    gaps = [int(n) / bound for n, ok in zip(res["best_length"], solved) if ok]
    net = b["coord_learner"].dqn
    n_params = sum(x.size for x in jax.tree.leaves(net.network.init(jax.random.PRNGKey(0),
                                                                    jnp.zeros(b["macro"].obs_dim))))
    judged = {}
    if b["env"].n_drawn:  # victims drawn at reset: the kept coordinators on the fixed judging draws
        episodes = greedy_episodes(trainer, res["best_params"], sc.judging_keys(b["env"]), params)
        j = sc.judge(b["env"], episodes)
        judged = {"normalized_score": j["normalized_score"], "fraction_all_saved": j["fraction_all_saved"],
                  "critical_saved": j["critical_saved"], "reference_return": j["reference_return"]}
    return {"trials": trials, **judged, "solved": int(sum(solved)),
            "reached_reference": int(sum(e is not None for e in res["episodes_to_optimal"])),
            "reference": b["reference"], "episodes_to_reference": res["episodes_to_optimal"],
            "median_gap": None if not gaps else round(float(np.median(gaps)), 3),
            "best_team_steps": [int(x) for x in res["best_length"]], "parameters": int(n_params),
            "outputs": int(net.n_actions), "seconds": round(seconds, 1)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--maps", nargs="+", default=MAPS, help="shipped map names or layout paths")
    p.add_argument("--kinds", nargs="+", default=("flat", "factored"), choices=("flat", "factored"))
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a config override for every run (repeatable), as in `jaxusar train --set`")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "coordinators.json")
    p.add_argument("--subpolicies", type=Path, metavar="RUN",
                   help="a hierarchical run folder (metrics.json, params/): over its trained sub-policies")
    args = p.parse_args()
    subpolicies = None if args.subpolicies is None else trained(args.subpolicies, args.trials)
    rows = {}
    for m in args.maps:
        for kind in args.kinds:
            try:
                row = run(m, kind, args.trials, args.seed, tuple(args.set), subpolicies)
            except config.ConfigError as err:  # the flat head past its limit (office)
                row = {"refused": str(err)}
            rows[f"{m}/{kind}"] = row
            print(f"{m:12s} {kind:9s} " + json.dumps({k: v for k, v in row.items() if k != "episodes_to_reference"}),
                  flush=True)
    args.out.write_text(json.dumps({"runs": rows, "seed": args.seed, "overrides": args.set,
                                    "subpolicies": None if args.subpolicies is None else str(args.subpolicies),
                                    "environment": environment_info()}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
