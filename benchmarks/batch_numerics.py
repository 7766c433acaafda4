"""Does a lane's training depend on how many lanes run beside it? (XLA's kernels, not the RNG.)

A trial's random numbers come from its own key, so they never depend on the batch; but XLA may compile a
vmapped update differently for different batch sizes, and round differently. This trains the first
``n`` sub-policy lanes of ``jaxusar train hierarchical`` (tuning seed 1000) for one chunk of ``--steps``
env steps, for each ``n`` of ``--lanes``, and compares the first lanes' learner state (params, optimizer,
replay) bit for bit with the widest batch's. Results on this project's Intel Xeon: benchmarks/README.md
("Finished trials stop costing").

    python benchmarks/batch_numerics.py --lanes 4 8 15 16 17 24 32 48 --steps 600
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from jaxusar import algos, config
from jaxusar.experiments import hierarchical


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lanes", type=int, nargs="+", default=[4, 8, 15, 16, 17, 24, 32, 48])
    ap.add_argument("--steps", type=int, default=600, help="env steps per lane (updates start at 500)")
    ap.add_argument("--map", default="two_rooms")
    args = ap.parse_args()
    if min(args.lanes) < 1:
        ap.error(f"--lanes must be >= 1, got {args.lanes}")
    cfg = config.load(None, ["seed=1000", f"train.chunk_steps={args.steps}", f"env.map={args.map}"],
                      defaults=algos.defaults("hierarchical"))
    n_tasks = len(hierarchical.build(cfg)["tasks"])
    widest = max(args.lanes)
    stage = hierarchical.Experiment(cfg, jax.random.split(jax.random.PRNGKey(1000), -(-widest // n_tasks))).chains[0][0]
    first = min(args.lanes)

    def learner(n):
        trainer = stage.trainer
        state = trainer.init(stage.keys[:n], jax.tree.map(lambda x: x[:n], stage.env_params))
        return [x[:first] for x in jax.tree.leaves(jax.device_get(trainer.run_chunk(state).trials.learner))]

    reference = learner(widest)
    print(f"{args.map}: the first {first} lanes after {args.steps} env steps, against a batch of {widest}")
    for n in sorted(args.lanes):
        same = all(np.array_equal(a, b) for a, b in zip(learner(n), reference))
        print(f"  {n:4d} lanes: {'identical' if same else 'differs'}")


if __name__ == "__main__":
    main()
