"""Where a reproduction's memory goes: every trainer's state, part by part, at a number of trials.

Sizes come from the shapes of each trainer's whole state (``jax.eval_shape`` of its init: nothing is
trained or allocated), split into the parts that grow with the run: replay rows, network parameters
with their target copy and optimizer, the kept best params and the chunk's param snapshots, the
learning curves, and the rest (env state, counters). Also the bytes one replay row takes, and what it
took before observations were stored as one-hot indices (format 1: uint8 features, obs and next_obs).
With ``--temporaries`` each trainer's chunk is also compiled (not run) and XLA's own account of it is
added: the temporary buffers a chunk needs beside its state (``memory_analysis``). The compiled code and
the interpreter are not in either: compare the total with the peak RSS ``jaxusar reproduce`` records in
results.json (``usage``).

    python benchmarks/memory.py --trials 64            # the full reproduction's trainers
    python benchmarks/memory.py --trials 32 --quick    # reproduce --quick
    python benchmarks/memory.py --trials 64 --temporaries
"""

from __future__ import annotations

import argparse
import json
import types

import jax
import numpy as np

from jaxusar.core import replay as rb
from jaxusar.core.replay import Replay
from jaxusar.experiments import reproduce, train

MB = 2 ** 20


def nbytes(tree) -> int:
    return sum(int(np.prod(x.shape)) * np.dtype(x.dtype).itemsize for x in jax.tree.leaves(tree))


def replays(tree) -> list[Replay]:
    return [x for x in jax.tree.leaves(tree, is_leaf=lambda x: isinstance(x, Replay)) if isinstance(x, Replay)]


def parts(state) -> dict[str, int]:
    """Bytes of one trainer state's parts (all lanes)."""
    t = state.trials
    replay = sum(nbytes(r.rows) for r in replays(t.learner))
    curves = nbytes([t.train_return, t.train_length, t.test_return, t.test_length, t.test_optimal, t.test_solved,
                     t.test_start_optimal, t.test_coverage])
    out = {"replay": replay, "params, target, optimizer": nbytes(t.learner) - replay,
           "best params and snapshots": nbytes([t.best_params, t.snaps]), "curves": curves}
    out["other"] = nbytes(state) - sum(out.values())
    return out


def row_bytes(state, dqn) -> tuple[int, int]:
    """(bytes of one replay row now, bytes it took in format 1, with obs and next_obs as uint8 features)."""
    now = rb.row_bytes(replays(state.trials.learner)[0])
    codes = 0 if dqn.codec is None else len(dqn.codec.sizes) * np.dtype(dqn.codec.dtype).itemsize
    return now, now + (0 if dqn.codec is None else 2 * (dqn.obs_dim - codes))


def temporaries(trainer, state) -> int:
    """Bytes of the temporary buffers XLA allocates for one chunk of ``state``'s shapes (compiled, not run)."""
    return jax.jit(trainer._run_chunk, donate_argnums=0).lower(state).compile().memory_analysis().temp_size_in_bytes


def measure(trials: int, quick: bool, temps: bool = False) -> dict:
    cfgs = reproduce.configs(quick)
    keys = train.trial_keys(cfgs["iql"].seed, trials)
    out = {}
    for cfg in cfgs.values():
        for chain in train.experiment(cfg, keys).chains:
            previous = None
            for stage in chain:
                env_params = stage.env_params
                if callable(env_params):  # built from the previous stage's results: sized on their shapes
                    env_params = jax.eval_shape(
                        lambda best, f=env_params: f(types.SimpleNamespace(results={"best_params": best})),
                        previous.trials.best_params)
                state = previous = jax.eval_shape(stage.trainer.init, stage.keys, env_params)
                learner = stage.trainer.learner
                now, before = row_bytes(state, getattr(learner, "dqn", None) or learner.critic)
                mb = parts(state)
                if temps:
                    mb["chunk temporaries (XLA)"] = temporaries(stage.trainer, state)
                out[stage.name] = {"lanes": int(len(stage.keys)), "row_bytes": now, "row_bytes_format1": before,
                                   "mb": {k: round(v / MB, 1) for k, v in mb.items()}}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=64)
    ap.add_argument("--quick", action="store_true", help="reproduce --quick's budgets")
    ap.add_argument("--temporaries", action="store_true", help="also compile each chunk for XLA's temporary buffers")
    args = ap.parse_args()
    if args.trials < 1:
        ap.error(f"--trials must be >= 1, got {args.trials}")
    rows = measure(args.trials, args.quick, args.temporaries)
    print(f"jaxusar reproduce{' --quick' if args.quick else ''} --trials {args.trials}: trainer states (MiB)")
    print(f"{'trainer':28s} {'lanes':>5s} {'row B':>6s} {'fmt1 B':>6s}  " + "  ".join(next(iter(rows.values()))["mb"]))
    for name, r in rows.items():
        print(f"{name:28s} {r['lanes']:5d} {r['row_bytes']:6d} {r['row_bytes_format1']:6d}  "
              + "  ".join(f"{v:>{len(k)}.1f}" for k, v in r["mb"].items()))
    total = sum(sum(r["mb"].values()) for r in rows.values())
    print(f"all trainers' states{' and chunk temporaries' if args.temporaries else ''} together: {total:.0f} MiB")
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
