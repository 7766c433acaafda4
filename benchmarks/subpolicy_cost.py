"""What one sub-policy env step costs, per lane, at a map's full batch (the paper's method, stage 1).

Builds the sub-policy trainer of ``--map`` for ``--trials`` trials (all tasks x trials as lanes), runs
one chunk of ``--steps`` env steps per lane (compile, learning starts), then times a second one; each
``--set`` list is one row. Each row after the first also says whether its learner state after the two
chunks is bit-identical to the first row's (the same seeds), so a setting meant to change only the cost
can be checked to change nothing else. Numbers in benchmarks/README.md ("Sub-policy cost on big maps").

    python benchmarks/subpolicy_cost.py --map office --trials 8 \\
        --set dqn.one_hot_input=false --set dqn.one_hot_input=true
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

from jaxusar import algos, config
from jaxusar.experiments import hierarchical


def cost(map_name: str, trials: int, steps: int, sets: list[str]):
    """(lanes, seconds of the second chunk, the learner state after it)."""
    cfg = config.load(None, [f"env.map={map_name}", f"train.chunk_steps={steps}"] + sets,
                      defaults=algos.defaults("hierarchical"))
    b = hierarchical.build(cfg)
    trainer, lanes = b["sub_trainer"], len(b["tasks"]) * trials
    params = jax.tree.map(lambda x: jnp.tile(x, (trials,) + (1,) * (x.ndim - 1)), b["task_params"])
    state = trainer.run_chunk(trainer.init(jax.random.split(jax.random.PRNGKey(0), lanes), env_params=params))
    jax.block_until_ready(state)
    t = time.perf_counter()
    state = jax.block_until_ready(trainer.run_chunk(state))
    return lanes, time.perf_counter() - t, state


def identical(a, b) -> bool:
    """Every leaf equal bit for bit (NaN, an unfilled record, equal to NaN)."""
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    return len(la) == len(lb) and all(x.shape == y.shape and bool(jnp.array_equal(x, y, equal_nan=True))
                                      for x, y in zip(la, lb))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--map", default="office")
    p.add_argument("--trials", type=int, default=8)
    p.add_argument("--steps", type=int, default=1000, help="env steps per lane in the timed chunk")
    p.add_argument("--set", dest="sets", action="append", default=[], help="one row's settings, comma-separated")
    args = p.parse_args()
    first = None
    for row in args.sets or [""]:
        sets = [s for s in row.split(",") if s]
        lanes, seconds, state = cost(args.map, args.trials, args.steps, sets)
        if first is None:
            first, same = state, ""
        else:
            same = f"; state {'bit-identical to' if identical(first, state) else 'differs from'} row 1"
        print(f"{args.map} {row or 'defaults':40s} {lanes} lanes: {seconds:6.1f} s per {args.steps} steps = "
              f"{1e6 * seconds / (args.steps * lanes):5.0f} us per lane-step{same}", flush=True)


if __name__ == "__main__":
    main()
