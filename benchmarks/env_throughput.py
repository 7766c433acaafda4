"""Env throughput: env-steps/s of the USAR grid world under jit(scan(vmap(step))), several maps side by side.

What one timed call does, per map and batch size B: ``--steps`` joint steps of B independent worlds in a
single jitted ``lax.scan``. Each step computes the observation (``env.step`` returns it; a checksum of it
is carried so XLA cannot drop it) and draws uniform random actions (generated inside the call, one
``jax.random.randint`` per chunk of ``--chunk`` steps). ``--resets``: ``trainer`` auto-resets as the trainer
does (``core.trainer``): every step also runs ``env.reset`` with a fresh key (drawing the victims anew on
a map that draws them) and takes its state and observation where the world is done (``env.step`` never
resets); ``none`` never resets (a done world steps on: its clock runs past the horizon and nothing else
changes but what the actions do), the cost of ``env.step`` alone. One env-step = one world advanced one
joint step, whatever its number of agents.

A map is ``NAME``, ``NAME:OBSERVATION`` (``full`` or ``view``) or ``NAME:OBSERVATION:ENCODING``
(``one_hot``, the default, or ``codes``: one integer per one-hot block, ``USAREnv``'s ``encoding``). Compile time is reported separately:
the first call (compile + run) is timed on its own; then ``--repeats`` rounds each time one call of every
map in turn (so a load that comes and goes on a shared machine falls on every map alike), and each map's
median is reported, with its ratio to the first map's.

``--parts`` also prices the parts of a step, per map, without resets: the step with its observation
unused (XLA drops it), then that plus ``env.observe`` of the new state, ``env.initial_state`` (the draw
of the victims, where the map draws them) or ``env.reset`` (a draw and its observation) with a fresh key;
each part's cost is its call's time less the first's, in ns per env-step.

``--against PATH`` also runs the first map with the package at PATH (a ``git worktree`` of an older
commit: ``PYTHONPATH=PATH``), in a process of its own, alternating with a process of this code, ``--rounds``
times each, and reports both medians over all their timed calls.

    python benchmarks/env_throughput.py                       # the maps below, batch 1024, 1000 steps
    python benchmarks/env_throughput.py --maps two_rooms --batches 1 64 1024 8192
    python benchmarks/env_throughput.py --against /tmp/base   # git worktree add /tmp/base 7a33613
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

MAPS = ["two_rooms", "two_rooms_rubble:full", "two_rooms_rubble:view", "minimap:full", "minimap:view",
        "two_rooms:full:codes", "minimap:view:codes"]


def make_env(spec: str, horizon: int):
    from jaxusar import envs

    name, observation, encoding = (spec.split(":") + ["", ""])[:3]
    settings = {"observation": observation} if observation else {}
    if encoding:
        settings["encoding"] = encoding
    return envs.make(name, horizon=horizon, **settings)


def make_run(env, batch: int, steps: int, chunk: int, reset_done: bool = True):
    """jit-ed ``run(key) -> (checksum, episodes_done)``: ``steps`` vmapped steps of ``batch`` worlds,
    resetting the done ones as the trainer does (``reset_done``) or never."""
    if steps % chunk:
        raise ValueError(f"--steps ({steps}) must be a multiple of --chunk ({chunk})")
    step = jax.vmap(env.step, in_axes=(None, 0, 0))
    reset = jax.vmap(env.reset)

    def one_step(carry, noise):
        state, checksum, episodes = carry
        actions, reset_keys = noise
        obs, state, reward, done, _ = step(None, state, actions)
        if reset_done:  # the trainer's auto-reset: a fresh start where done
            obs0, state0 = reset(reset_keys)
            pick = lambda a, b: jnp.where(done.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)
            state, obs = jax.tree.map(pick, state0, state), pick(obs0, obs)
        checksum = checksum + obs.sum() + reward.sum()
        return (state, checksum, episodes + done.sum()), None

    def one_chunk(carry, key):
        k_act, k_reset = jax.random.split(key)
        actions = jax.random.randint(k_act, (chunk, batch, env.n_agents), 0, 4, jnp.int32)
        return jax.lax.scan(one_step, carry, (actions, jax.random.split(k_reset, (chunk, batch))))[0], None

    @jax.jit
    def run(key):
        k_start, k_run = jax.random.split(key)
        _, state = reset(jax.random.split(k_start, batch))
        carry = (state, jnp.zeros((), jnp.float32), jnp.zeros((), jnp.int32))
        (_, checksum, episodes), _ = jax.lax.scan(one_chunk, carry, jax.random.split(k_run, steps // chunk))
        return checksum, episodes

    return run


PARTS = {"step, observation unused": None,
         "observe": lambda env, state, key: env.observe(state).sum(),
         "initial_state": lambda env, state, key: sum(
             x.sum() for x in jax.tree.leaves(env.initial_state(key if env.n_drawn else None))),
         "reset": lambda env, state, key: env.reset(key)[0].sum()}


def make_part_run(env, part, batch: int, steps: int, chunk: int):
    """jit-ed ``run(key)``: ``steps`` steps of ``batch`` worlds, never reset, the observation unused; and
    ``part(env, state, key)`` on every new state (None: nothing more)."""
    step = jax.vmap(env.step, in_axes=(None, 0, 0))

    def one_step(carry, noise):
        state, checksum = carry
        actions, keys = noise
        _, state, reward, _, _ = step(None, state, actions)
        extra = 0.0 if part is None else jax.vmap(lambda s, k: part(env, s, k))(state, keys).sum()
        return (state, checksum + reward.sum() + extra), None

    def one_chunk(carry, key):
        k_act, k_part = jax.random.split(key)
        actions = jax.random.randint(k_act, (chunk, batch, env.n_agents), 0, 4, jnp.int32)
        return jax.lax.scan(one_step, carry, (actions, jax.random.split(k_part, (chunk, batch))))[0], None

    @jax.jit
    def run(key):
        _, state = jax.vmap(env.reset)(jax.random.split(key, batch))
        carry = (state, jnp.zeros((), jnp.float32))
        return jax.lax.scan(one_chunk, carry, jax.random.split(key, steps // chunk))[0][1]

    return run


def measure_parts(spec: str, batch: int, steps: int, chunk: int, repeats: int, horizon: int) -> dict:
    """{part: ns per env-step}: the first part's time per env-step, then each other's on top of it."""
    env = make_env(spec, horizon)
    runs = {name: make_part_run(env, part, batch, steps, chunk) for name, part in PARTS.items()}
    times = {name: [] for name in runs}
    for name, run in runs.items():
        jax.block_until_ready(run(jax.random.key(0)))
    for i in range(repeats):
        for name, run in runs.items():
            t0 = time.perf_counter()
            jax.block_until_ready(run(jax.random.key(i + 1)))
            times[name].append(time.perf_counter() - t0)
    ns = {name: 1e9 * statistics.median(t) / (batch * steps) for name, t in times.items()}
    first = next(iter(ns))
    return {name: v if name == first else v - ns[first] for name, v in ns.items()}


def measure(specs: list[str], resets: list[str], batch: int, steps: int, chunk: int, repeats: int,
            horizon: int) -> list[dict]:
    """Every (map, reset)'s first call, then ``repeats`` rounds of one timed call each; per case its median."""
    runs, rows = {}, {}
    for spec in specs:
        env = make_env(spec, horizon)
        for reset in resets:
            runs[spec, reset] = make_run(env, batch, steps, chunk, reset == "trainer")
            t0 = time.perf_counter()
            jax.block_until_ready(runs[spec, reset](jax.random.key(0)))
            rows[spec, reset] = {"map": spec, "reset": reset, "batch": batch, "steps": steps,
                                 "env_steps": batch * steps, "agents": env.n_agents,
                                 "obs_shape": list(getattr(env, "obs_shape", (env.obs_dim,))),  # older commits: none
                                 "first_call_s": time.perf_counter() - t0, "times_s": []}
    for i in range(repeats):
        for case, run in runs.items():
            t0 = time.perf_counter()
            _, episodes = jax.block_until_ready(run(jax.random.key(i + 1)))
            rows[case]["times_s"].append(time.perf_counter() - t0)
            rows[case]["episodes_done"] = int(episodes)
    for r in rows.values():
        r["median_s"] = statistics.median(r["times_s"])
        r["env_steps_per_s"] = r["env_steps"] / r["median_s"]
    return list(rows.values())


def machine() -> dict:
    try:
        from jaxusar.experiments.train import cpu_name

        cpu = cpu_name()
    except ImportError:
        cpu = platform.processor()
    return {"cpu": cpu, "cpu_count": os.cpu_count(), "backend": jax.default_backend(),
            "devices": [str(d) for d in jax.devices()], "jax": jax.__version__, "python": platform.python_version()}


def against(path: str, spec: str, reset: str, args) -> dict:
    """The first map's numbers with this code and with the package at ``path``, processes alternating."""
    common = ["--maps", spec, "--resets", reset, "--batches", str(args.batches[-1]), "--steps",
              str(args.steps), "--chunk", str(args.chunk), "--repeats", str(args.repeats), "--horizon",
              str(args.horizon), "--json"]
    here = str(Path(__file__).resolve().parents[1])
    times = {"this": [], "against": []}
    for _ in range(args.rounds):
        for side, root in (("this", here), ("against", path)):
            env = {**os.environ, "PYTHONPATH": root}
            out = subprocess.run([sys.executable, __file__, *common], env=env, check=True, capture_output=True,
                                 text=True, cwd=root).stdout
            (row,) = json.loads(out.strip().splitlines()[-1])["rows"]
            times[side] += row["times_s"]
    batch_steps = args.batches[-1] * args.steps
    result = {"map": spec, "reset": reset, "against": path, "rounds": args.rounds,
              **{f"{side}_times_s": t for side, t in times.items()}}
    for side, t in times.items():
        result[f"{side}_env_steps_per_s"] = batch_steps / statistics.median(t)
    result["ratio"] = result["this_env_steps_per_s"] / result["against_env_steps_per_s"]
    return result


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--maps", nargs="+", default=MAPS, help="NAME or NAME:OBSERVATION; ratios are to the first")
    p.add_argument("--resets", nargs="+", choices=["trainer", "none"], default=["trainer", "none"],
                   help="auto-reset as the trainer (trainer) or never (none)")
    p.add_argument("--batches", type=int, nargs="+", default=[1024])
    p.add_argument("--steps", type=int, default=1000, help="joint steps per timed call")
    p.add_argument("--chunk", type=int, default=100, help="steps per pre-generated block of random actions")
    p.add_argument("--repeats", type=int, default=5, help="timed rounds after the compile calls (median)")
    p.add_argument("--horizon", type=int, default=100)
    p.add_argument("--against", metavar="PATH", help="also time the first map with the package at PATH")
    p.add_argument("--rounds", type=int, default=3, help="--against: processes of each side, alternating")
    p.add_argument("--parts", action="store_true", help="also price the parts of a step (module doc)")
    p.add_argument("--json", action="store_true", help="print the result as one JSON line, write no file")
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "env_throughput_usar.json"))
    args = p.parse_args(argv)

    info = machine()
    say = (lambda *a: None) if args.json else print
    say(f"{info['cpu']} x{info['cpu_count']}, jax {jax.__version__} ({info['backend']})")
    say(f"{'map':<24} {'reset':<8} {'batch':>6} {'compile+1st s':>13} {'median s':>9} {'env-steps/s':>13} "
        f"{'ratio':>6} {'episodes':>9}")
    rows = []
    for batch in args.batches:
        measured = measure(args.maps, args.resets, batch, args.steps, args.chunk, args.repeats, args.horizon)
        first = {r["reset"]: r for r in measured if r["map"] == args.maps[0]}
        for r in sorted(measured, key=lambda r: args.resets.index(r["reset"])):
            r["ratio_to_first"] = r["env_steps_per_s"] / first[r["reset"]]["env_steps_per_s"]
            say(f"{r['map']:<24} {r['reset']:<8} {batch:>6} {r['first_call_s']:>13.2f} {r['median_s']:>9.4f} "
                f"{r['env_steps_per_s']:>13,.0f} {r['ratio_to_first']:>6.2f} {r['episodes_done']:>9}")
        rows += measured
    result = {"benchmark": "env_throughput", "maps": args.maps, "horizon": args.horizon, "steps": args.steps,
              "chunk": args.chunk, "repeats": args.repeats, "resets": args.resets, "machine": info, "rows": rows}
    if args.json:
        print(json.dumps(result))
        return result
    if args.parts:
        batch = args.batches[-1]
        say(f"\nparts, ns per env-step at batch {batch}, no resets (the first: the step alone; then each on top of it)")
        say(f"{'map':<24} " + " ".join(f"{name:>24}" for name in PARTS))
        result["parts"] = {}
        for spec in args.maps:
            result["parts"][spec] = ns = measure_parts(spec, batch, args.steps, args.chunk, args.repeats, args.horizon)
            say(f"{spec:<24} " + " ".join(f"{v:>24.0f}" for v in ns.values()))
    if args.against:
        result["against"] = []
        for reset in args.resets:
            result["against"].append(a := against(args.against, args.maps[0], reset, args))
            print(f"{a['map']} ({reset} reset) at batch {args.batches[-1]}, {a['rounds']} processes each, "
                  f"alternating: {a['this_env_steps_per_s']:,.0f} env-steps/s here, "
                  f"{a['against_env_steps_per_s']:,.0f} at {a['against']} (ratio {a['ratio']:.2f})")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")
    return result


if __name__ == "__main__":
    main()
