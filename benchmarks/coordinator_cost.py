"""What the coordinator stage (the paper's method, stage 2) costs at several trial counts, over trained sub-policies.

Reads the kept sub-policy params of a finished ``jaxusar train hierarchical`` or ``jaxusar reproduce``
run (``--run``: its hierarchical folder, with ``params/trial_<j>.msgpack``), and for each ``--trials N``
trains the coordinator of trials 0..N-1 over them, as the run's stage 2 does (same config, seed and trial
keys), timing its sub-policy tables, its compile and its training one after the other in one process.
Reported per N: seconds, the ratio to the smallest N, and what was learned (episodes to optimal and best
team test per trial), so that two commits' rows can be checked for equal results as well as compared for
time. Intel Xeon and AMD EPYC numbers in benchmarks/README.md ("The coordinator's cost").

    python benchmarks/coordinator_cost.py --run results/two_rooms_64trials/hierarchical --trials 8 32 64
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from jaxusar import algos, config
from jaxusar.experiments import hierarchical
from jaxusar.experiments.train import environment_info, trial_keys


def load_subpolicies(run: Path, trials: int):
    """The kept sub-policy params of trials 0..trials-1, stacked: a leading [trial, task] axis pair."""
    blobs = []
    for j in range(trials):
        path = run / "params" / f"trial_{j}.msgpack"
        if not path.exists():
            raise SystemExit(f"{path} is missing: expected a finished hierarchical run's folder with at least "
                             f"{trials} trials (its params/ folder)")
        blobs.append(serialization.msgpack_restore(path.read_bytes())["subpolicies"])
    return jax.tree.map(lambda *x: jnp.stack(x), *blobs)


def cost(run: Path, trials: int, sets: list[str], drop_finished: bool = False) -> dict:
    metrics = run / "metrics.json"  # the run's own config (map, seed, settings), then --set
    defaults = json.loads(metrics.read_text())["config"] if metrics.exists() else algos.defaults("hierarchical")
    cfg = config.load(None, sets, defaults=defaults)
    b = hierarchical.build(cfg)
    trainer, keys = b["coord_trainer"], trial_keys(cfg.seed, trials)
    trainer.drop_finished |= drop_finished
    start = time.perf_counter()
    env_params = b["coordinator_params"](load_subpolicies(run, trials))
    tabulated = time.perf_counter()
    state = trainer.init(keys, env_params)
    trainer.compile(state)
    compiled = time.perf_counter()
    state = trainer.train(keys, state=state)
    res = trainer.results(state)
    done = time.perf_counter()
    return {"trials": trials, "tabulate_seconds": round(tabulated - start, 2),
            "compile_seconds": round(compiled - tabulated, 2), "run_seconds": round(done - compiled, 2),
            "episodes_to_optimal": res["episodes_to_optimal"], "best_team_test_steps": res["best_length"].tolist(),
            "best_team_test_return": res["best_return"].tolist(), "chunks": int(state.chunk)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", type=Path, required=True, help="a finished hierarchical run's folder (with params/)")
    p.add_argument("--trials", type=int, nargs="+", default=[8, 32])
    p.add_argument("--set", dest="sets", action="append", default=[], help="a setting, as on `jaxusar train`")
    p.add_argument("--drop-finished", action="store_true",
                   help="run stopped trials' chunks in smaller batches (the coordinator's default: not)")
    p.add_argument("--out", type=Path, help="also write the rows here (JSON)")
    args = p.parse_args()
    rows = []
    for n in sorted(args.trials):
        row = cost(args.run, n, args.sets, args.drop_finished)
        base = rows[0]["run_seconds"] if rows else row["run_seconds"]
        eto = [e for e in row["episodes_to_optimal"] if e is not None]
        print(f"{n:4d} trials: tables {row['tabulate_seconds']:5.1f} s, compile {row['compile_seconds']:6.1f} s, "
              f"run {row['run_seconds']:7.1f} s "
              f"({row['run_seconds'] / base:5.2f}x the first row), {row['chunks']} chunks; optimal in "
              f"{len(eto)}/{n}, median {np.median(eto) if eto else float('nan'):g} episodes", flush=True)
        rows.append(row)
    if args.out:
        args.out.write_text(json.dumps({"run": str(args.run), "sets": args.sets,
                                        "drop_finished": args.drop_finished, "rows": rows,
                                        "environment": environment_info()}, indent=1))


if __name__ == "__main__":
    main()
