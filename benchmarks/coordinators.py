"""The flat (paper) and factored coordinators side by side, over exact sub-policies.

Exact sub-policies (``subpolicies.exact_subpolicies``: shortest-path actions from the planner's
distance tables) isolate the coordinator: each map's default coordinator settings, 8 trials
(``--seed``), both kinds on the same keys, one after the other in one process. Reported per map and
kind: trials whose greedy team test triaged every victim, trials that reached the reference (the exact
optimum, or the lower bound where the joint search is out of reach), the median best team test as a
ratio to the lower bound, the network's parameters, and compile + run seconds; on a map whose victims are
drawn, each trial's kept coordinator judged on the fixed draws (``scripted.judge``: normalized score,
draws with every victim saved, critical victims saved).

    python benchmarks/coordinators.py            # writes benchmarks/results/coordinators.json
    python benchmarks/coordinators.py --maps office --kinds factored \
        --set hierarchical.coordinator.block_patience=2 --out /tmp/office.json   # one variant, one map
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxusar import algos, config
from jaxusar.algos import coordinator as coord
from jaxusar.algos import subpolicies as sp
from jaxusar.experiments import hierarchical
from jaxusar.experiments import scripted as sc
from jaxusar.experiments.train import environment_info, greedy_episodes

MAPS = ("two_rooms", "three_rooms", "four_rooms", "office")


def run(map_name: str, kind: str, trials: int, seed: int, overrides: tuple[str, ...] = ()) -> dict:
    cfg = config.load(None, [f"env.map={map_name}", f"hierarchical.coordinator.kind={kind}", f"seed={seed}",
                             *overrides], defaults=algos.defaults("hierarchical"))
    probe = hierarchical.build(cfg)
    act, tables = sp.exact_subpolicies(probe["subtask_env"], probe["task_params"])
    b = hierarchical.build(cfg, subpolicy_act=act)
    keys = jax.random.split(jax.random.PRNGKey(seed), trials)
    params = coord.CoordinatorParams(subpolicy=jnp.broadcast_to(tables, (trials, *tables.shape)))
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
    args = p.parse_args()
    rows = {}
    for m in args.maps:
        for kind in args.kinds:
            try:
                row = run(m, kind, args.trials, args.seed, tuple(args.set))
            except config.ConfigError as err:  # the flat head past its limit (office)
                row = {"refused": str(err)}
            rows[f"{m}/{kind}"] = row
            print(f"{m:12s} {kind:9s} " + json.dumps({k: v for k, v in row.items() if k != "episodes_to_reference"}),
                  flush=True)
    args.out.write_text(json.dumps({"runs": rows, "seed": args.seed, "overrides": args.set,
                                    "environment": environment_info()}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
