"""Env throughput: env-steps/s of the USAR grid world under jit(scan(vmap(step))).

What one timed call does, per batch size B: ``--steps`` joint steps of B independent worlds in a
single jitted ``lax.scan``. Each step computes the observation (``env.step`` returns it; a checksum
of it is carried so XLA cannot drop it), draws uniform random actions (generated inside the call,
one ``jax.random.randint`` per chunk of ``--chunk`` steps), and resets the worlds that are done with
``jnp.where`` on the state (``env.step`` never resets). One env-step = one world advanced one joint step.

Compile time is reported separately: the first call (compile + run) is timed on its own, then the
median of ``--repeats`` calls (each ended with ``block_until_ready``).

    python benchmarks/env_throughput.py                       # batches 1 64 1024 8192, 1000 steps
    python benchmarks/env_throughput.py --batches 1024 --steps 2000 --out /tmp/t.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from jaxusar import envs
from jaxusar.experiments.train import cpu_name


def make_run(env, batch: int, steps: int, chunk: int):
    """jit-ed ``run(key) -> (checksum, episodes_done)``: ``steps`` vmapped steps of ``batch`` worlds."""
    if steps % chunk:
        raise ValueError(f"--steps ({steps}) must be a multiple of --chunk ({chunk})")
    step = jax.vmap(env.step, in_axes=(None, 0, 0))
    _, start = env.reset(None)
    start_b = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), start)

    def one_step(carry, actions):
        state, checksum, episodes = carry
        obs, state, reward, done, _ = step(None, state, actions)
        # Auto-reset outside the env: where done, take the start state.
        state = jax.tree.map(
            lambda s0, s: jnp.where(done.reshape((-1,) + (1,) * (s.ndim - 1)), s0, s), start_b, state)
        checksum = checksum + obs.sum() + reward.sum()
        return (state, checksum, episodes + done.sum()), None

    def one_chunk(carry, key):
        actions = jax.random.randint(key, (chunk, batch, env.n_agents), 0, envs.N_ACTIONS, jnp.int32)
        return jax.lax.scan(one_step, carry, actions)[0], None

    @jax.jit
    def run(key):
        keys = jax.random.split(key, steps // chunk)
        carry = (start_b, jnp.zeros((), jnp.float32), jnp.zeros((), jnp.int32))
        (_, checksum, episodes), _ = jax.lax.scan(one_chunk, carry, keys)
        return checksum, episodes

    return run


def measure(env, batch: int, steps: int, chunk: int, repeats: int) -> dict:
    run = make_run(env, batch, steps, chunk)
    key = jax.random.key(0)
    t0 = time.perf_counter()
    jax.block_until_ready(run(key))
    first = time.perf_counter() - t0
    times = []
    for i in range(repeats):
        t0 = time.perf_counter()
        _, episodes = jax.block_until_ready(run(jax.random.key(i + 1)))
        times.append(time.perf_counter() - t0)
    median = statistics.median(times)
    return {
        "batch": batch, "steps": steps, "env_steps": batch * steps,
        "first_call_s": first, "compile_s": max(first - median, 0.0), "median_s": median,
        "times_s": times, "env_steps_per_s": batch * steps / median, "episodes_done": int(episodes),
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--map", default="two_rooms")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 8192])
    p.add_argument("--steps", type=int, default=1000, help="joint steps per timed call")
    p.add_argument("--chunk", type=int, default=100, help="steps per pre-generated block of random actions")
    p.add_argument("--repeats", type=int, default=5, help="timed calls after the compile call (median)")
    p.add_argument("--horizon", type=int, default=100)
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "env_throughput.json"))
    args = p.parse_args(argv)

    env = envs.make(args.map, horizon=args.horizon)
    machine = {
        "cpu": cpu_name(), "cpu_count": os.cpu_count(), "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()], "jax": jax.__version__, "python": platform.python_version(),
    }
    print(f"{env}\n{machine['cpu']} x{machine['cpu_count']}, jax {jax.__version__} ({machine['backend']})")
    print(f"{'batch':>6} {'steps':>6} {'compile+1st s':>13} {'median s':>9} {'env-steps/s':>13} {'episodes':>9}")
    rows = []
    for batch in args.batches:
        r = measure(env, batch, args.steps, args.chunk, args.repeats)
        rows.append(r)
        print(f"{batch:>6} {args.steps:>6} {r['first_call_s']:>13.2f} {r['median_s']:>9.4f} "
              f"{r['env_steps_per_s']:>13,.0f} {r['episodes_done']:>9}")
    result = {"benchmark": "env_throughput", "map": args.map, "horizon": args.horizon, "steps": args.steps,
              "chunk": args.chunk, "repeats": args.repeats, "machine": machine, "rows": rows}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")
    return result


if __name__ == "__main__":
    main()
