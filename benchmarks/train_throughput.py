"""Trainer throughput vs the bare-update ceiling, side by side in one run (issue: learning core).

For a config (default: the IQL defaults), measures
  * trainer: env steps/s of the full N-trial trainer (act, env step, replay, updates, greedy tests),
    median over timed chunks after a compile chunk;
  * ceiling: the same number of gradient updates alone (same network, batch, trials x learners,
    vmapped, replay sampling included), expressed in env steps/s (updates/s x train_every);
  * ratio trainer / ceiling (aim: >= 0.5), and the flashbax item buffer's add+sample cost beside ours.

With several algorithms (``--algo iql vdn qmix``) each gets the same measurements, their timed chunks
taken in turns so that the machine's drift hits all alike, and each is reported as wall time per env step
relative to the first (issue: value decomposition within 1.2x of IQL).

    python benchmarks/train_throughput.py --trials 8 [--algo iql vdn qmix] [--set dqn.hidden=[32,32] ...]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from jaxusar import algos, config
from jaxusar.core import replay as rb
from jaxusar.experiments.train import build, environment_info


def timed(fn, *args, repeats=3):
    """(first call seconds incl. compile, median of `repeats` further calls)."""
    t = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return first, statistics.median(times)


def trainer_throughput(trainers: dict, trials: int, chunks: int) -> tuple[dict, dict]:
    """({name: throughput}, {name: final state}): one compile chunk each, then `chunks` timed rounds of one
    chunk per trainer in turn; the median chunk per trainer."""
    states, first, times = {}, {}, {name: [] for name in trainers}

    def chunk(name):
        t = time.perf_counter()
        states[name] = trainers[name].run_chunk(states[name])
        jax.block_until_ready(states[name].step)
        return time.perf_counter() - t

    for name, trainer in trainers.items():
        states[name] = trainer.init(jax.random.split(jax.random.PRNGKey(0), trials))
        first[name] = chunk(name)
    for _ in range(chunks):
        for name in trainers:
            times[name].append(chunk(name))
    out = {}
    for name, trainer in trainers.items():
        per_chunk = statistics.median(times[name])
        out[name] = {"compile_and_first_chunk_s": first[name], "chunk_s": per_chunk,
                     "env_steps_per_s": trials * trainer.chunk_steps / per_chunk}
    return out, states


def update_ceiling(trainer, state, trials, updates):
    """`updates` vmapped learner updates in one scan, on the trainer's filled replay buffers."""
    learner = trainer.learner
    shapes = {k: v for k, v in learner.update_noise.items()}

    def run(ls, key):
        # randomness drawn up front, as the trainer does
        noise = {n: jax.random.uniform(jax.random.fold_in(key, i), (updates, trials, *s))
                 for i, (n, s) in enumerate(sorted(shapes.items()))}
        ls, _ = jax.lax.scan(lambda ls, nz: (jax.vmap(learner.update)(ls, nz), None), ls, noise)
        return ls

    fn = jax.jit(run)
    first, med = timed(fn, state.trials.learner, jax.random.PRNGKey(1))
    return {"compile_s": first, "updates_per_s": trials * updates / med,
            "env_steps_per_s": trials * updates * trainer.train_every / med}


def replay_comparison(capacity=50_000, batch=32, obs_dim=60, n=2000):
    """Our replay vs flashbax's item buffer: n add+sample rounds in one scan (if flashbax is installed)."""
    row = {"obs": jnp.zeros((obs_dim,), jnp.uint8), "action": jnp.zeros((), jnp.int32),
           "reward": jnp.zeros(()), "next_obs": jnp.zeros((obs_dim,), jnp.uint8), "terminal": jnp.zeros((), bool)}
    out = {}

    def ours(key):
        buf = rb.init(row, capacity)

        def body(buf, k):
            buf = rb.add(buf, row)
            return buf, rb.sample(buf, jax.random.uniform(k, (batch,)))["reward"].sum()

        return jax.lax.scan(body, buf, jax.random.split(key, n))[1]

    out["jaxusar_replay_us_per_add_sample"] = timed(jax.jit(ours), jax.random.PRNGKey(0))[1] / n * 1e6
    try:
        import flashbax as fbx
    except ImportError:
        out["flashbax"] = "not installed (pip install flashbax==0.1.3)"
        return out
    fb = fbx.make_item_buffer(max_length=capacity, min_length=1, sample_batch_size=batch, add_batches=False)

    def theirs(key):
        state = fb.init(row)

        def body(state, k):
            state = fb.add(state, row)
            return state, fb.sample(state, k).experience["reward"].sum()

        return jax.lax.scan(body, state, jax.random.split(key, n))[1]

    out["flashbax_item_buffer_us_per_add_sample"] = timed(jax.jit(theirs), jax.random.PRNGKey(0))[1] / n * 1e6
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algo", nargs="+", default=["iql"], help="flat learners to measure (default: iql)")
    p.add_argument("--config", default=None)
    p.add_argument("--set", dest="sets", action="append", default=[])
    p.add_argument("--trials", type=int, default=8)
    p.add_argument("--chunks", type=int, default=3, help="timed chunks after the compile chunk")
    p.add_argument("--out", default="benchmarks/results/train_throughput.json")
    args = p.parse_args(argv)
    cfgs = {name: config.load(args.config, args.sets, defaults=algos.defaults(name)) for name in args.algo}
    trainers = {name: build(cfg)[3] for name, cfg in cfgs.items()}
    throughput, states = trainer_throughput(trainers, args.trials, args.chunks)
    base = throughput[args.algo[0]]["env_steps_per_s"]
    runs = []
    for name, trainer in trainers.items():
        cfg, tr = cfgs[name], throughput[name]
        ceiling = update_ceiling(trainer, states[name], args.trials, updates=trainer.iters)
        runs.append({"algo": name, "trials": args.trials, "dqn": cfg.to_dict()["dqn"], "env": cfg.to_dict()["env"],
                     "chunk_steps": trainer.chunk_steps, "trainer": tr, "ceiling": ceiling,
                     "ratio": tr["env_steps_per_s"] / ceiling["env_steps_per_s"],
                     "wall_per_env_step_vs_first": base / tr["env_steps_per_s"]})
        print(f"{name} on {cfg.env.map}, {args.trials} trials, hidden {cfg.dqn.hidden}, batch {cfg.dqn.batch_size}, "
              f"update every {cfg.dqn.train_every} env steps")
        print(f"  trainer : {tr['env_steps_per_s']:>12,.0f} env steps/s  (chunk {tr['chunk_s']:.2f}s, "
              f"compile+first chunk {tr['compile_and_first_chunk_s']:.1f}s)")
        print(f"  ceiling : {ceiling['env_steps_per_s']:>12,.0f} env steps/s  ({ceiling['updates_per_s']:,.0f} "
              "updates/s, bare vmapped updates)")
        print(f"  ratio   : {runs[-1]['ratio']:.2f}")
        if len(trainers) > 1:
            print(f"  wall per env step: {runs[-1]['wall_per_env_step_vs_first']:.2f}x {args.algo[0]}'s")
    result = {"runs": runs, "replay": replay_comparison(), "environment": environment_info()}
    for k, v in result["replay"].items():
        print(f"  {k}: {v if isinstance(v, str) else f'{v:.2f}'}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.exit(main())
