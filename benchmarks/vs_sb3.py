"""jaxusar vs Stable-Baselines3 DQN on one sub-task, side by side in one run (issue 7).

Task: agent 1 (the bottom medic) NAVIGATE-TO-TOP-ROOM on the pseudo-reward (+100 on reaching the
room, -1 per step), from the medic's start only, horizon 300 (``usar_adapters.navigation_subtask``;
optimum 11 steps). Both sides get the same settings (``MATCHED`` below, the package's sub-policy
settings with plain DQN targets) and the same number of env steps per trial.

* jaxusar: ``jaxusar.core.Trainer`` + ``jaxusar.algos.subpolicies.make_learner`` on the package's
  ``SubtaskEnv``, all trials in one vmapped call; wall time = ahead-of-time compile + every chunk.
* SB3: ``stable_baselines3.DQN`` (PyTorch CPU) on ``usar_adapters.SubtaskGymEnv``, seeds one after
  another as a user would; wall time per seed = model construction + ``learn``. A callback runs one
  deterministic test episode on a second env instance every ``test_every`` training episodes (the
  jaxusar trainer's cadence); its time is measured and reported apart.

Episodes to optimal: the training-episode count at the first greedy test that reaches the room in
the shortest path. Also reported: where SB3's time goes (env step, action selection, gradient
steps, the rest of its loop), timed inside the same run.

    python benchmarks/vs_sb3.py                          # 8 seeds x 30000 env steps (about 4 minutes)
    python benchmarks/vs_sb3.py --seeds 2 --steps 4000   # smoke run
    python benchmarks/vs_sb3.py --compile-cache /tmp/jaxusar-xla --out benchmarks/results/vs_sb3_cache.json
                                                         # jaxusar cold (compiles), then 3 warm (load programs)
    python benchmarks/vs_sb3.py --jax-threads 1 --torch-threads 1   # each side on one thread per op
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import usar_adapters as ua
from jaxusar import config
from jaxusar.algos import subpolicies as sp
from jaxusar.config import DQNConfig, TrainConfig
from jaxusar.core import Trainer
from jaxusar.experiments.train import environment_info
from jaxusar.experiments.usage import enable_compile_cache
from train_throughput import update_ceiling

# One setting, applied to both sides: the package's sub-policy settings (configs/hierarchical.yaml),
# except double_dqn (SB3's DQN has none).
MATCHED = dict(hidden=[64, 64], lr=5e-4, gamma=0.99, batch_size=32, buffer_capacity=50_000, learning_starts=500,
               train_every=4, target_update_every=250, tau=1.0, double_dqn=False, loss="huber", max_grad_norm=10.0,
               eps_start=1.0, eps_end=0.05, eps_decay_steps=20_000)
TEST_EVERY = 10  # training episodes between greedy tests (configs/hierarchical.yaml, paper Fig. 4)


# -- jaxusar ----------------------------------------------------------------------------------------
def start_xla_cpu(threads: int | None) -> int:
    """Start JAX's CPU backend with an intra-op thread pool of ``threads`` threads (None: XLA's default, one
    per CPU this process may run on); returns the pool's size. XLA sizes the pool from the process's CPU
    affinity when the backend starts, so the process runs on ``threads`` CPUs for that moment only."""
    from jax._src import xla_bridge

    cpus = sorted(os.sched_getaffinity(0))
    if threads is None or threads >= len(cpus):
        jax.devices()
        return len(cpus)
    if xla_bridge.backends_are_initialized():
        raise SystemExit("--jax-threads: JAX's backend started before the thread pool could be sized")
    os.sched_setaffinity(0, cpus[:threads])
    try:
        jax.devices()
    finally:
        os.sched_setaffinity(0, cpus)
    return threads


def run_jaxusar(task: ua.Subtask, trials: int, steps: int, chunk_steps: int, seed: int = 0) -> dict:
    dqn = config.from_dict(DQNConfig, MATCHED)
    episodes = steps // task.optimal_steps + 1  # more than a trial can finish: recording never stops early
    train = TrainConfig(episodes=episodes, test_every=TEST_EVERY, chunk_steps=min(chunk_steps, steps))
    learner = sp.make_learner(task.senv, dqn)
    trainer = Trainer(task.senv, learner, train, learning_starts=dqn.learning_starts, train_every=dqn.train_every,
                      optimal_steps=task.optimal_steps, min_episode_steps=task.optimal_steps)
    if steps % trainer.chunk_steps:
        raise SystemExit(f"--steps {steps} must be a multiple of the chunk ({trainer.chunk_steps} env steps)")
    start = time.perf_counter()
    keys = jax.random.split(jax.random.PRNGKey(seed), trials)
    params = jax.tree.map(lambda x: jnp.tile(jnp.asarray(x)[None], (trials,) + (1,) * np.ndim(x)), task.params)
    state = trainer.init(keys, params)
    jax.block_until_ready(state)
    init_s = time.perf_counter() - start
    compile_s = trainer.compile(state)
    chunk_s = []
    for _ in range(steps // trainer.chunk_steps):
        t = time.perf_counter()
        state = trainer.run_chunk(state)
        jax.block_until_ready(state.step)
        chunk_s.append(time.perf_counter() - t)
    wall = time.perf_counter() - start
    res = trainer.results(state)
    assert int(state.step) == steps
    # where the time went (measured after the timed run): init again (cached), and the chunk's updates alone
    t = time.perf_counter()
    jax.block_until_ready(trainer.init(keys, params))
    init_cached_s = time.perf_counter() - t
    ceiling = update_ceiling(trainer, state, trials, updates=trainer.iters)
    updates_alone_s = steps // trainer.train_every * trials / ceiling["updates_per_s"]
    return {"trials": trials, "env_steps_per_trial": steps, "chunk_steps": trainer.chunk_steps,
            "wall_s": wall, "init_s": init_s, "compile_s": compile_s, "run_s": sum(chunk_s), "chunk_s": chunk_s,
            "init_cached_s": init_cached_s, "updates_alone_s": updates_alone_s, "update_ceiling": ceiling,
            "episodes_to_optimal": res["episodes_to_optimal"],
            "training_episodes": np.asarray(state.trials.episodes).tolist(),
            "best_test_steps": np.asarray(res["best_length"]).tolist()}


# -- Stable-Baselines3 -------------------------------------------------------------------------------
def sb3_settings(steps: int) -> dict:
    m = MATCHED
    return dict(learning_rate=m["lr"], buffer_size=m["buffer_capacity"], learning_starts=m["learning_starts"],
                batch_size=m["batch_size"], tau=m["tau"], gamma=m["gamma"], train_freq=m["train_every"],
                gradient_steps=1,
                # SB3 counts target_update_interval in env steps; jaxusar counts updates (one per train_every steps)
                target_update_interval=m["target_update_every"] * m["train_every"],
                exploration_fraction=m["eps_decay_steps"] / steps, exploration_initial_eps=m["eps_start"],
                exploration_final_eps=m["eps_end"], max_grad_norm=m["max_grad_norm"],
                policy_kwargs=dict(net_arch=list(m["hidden"])))  # ReLU, Adam, smooth L1 (Huber) are SB3's defaults


class Stopwatch:
    """Accumulates the seconds spent inside wrapped callables."""

    def __init__(self):
        self.seconds, self.calls = {}, {}

    def wrap(self, name, fn):
        self.seconds[name], self.calls[name] = 0.0, 0

        def timed(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[name] += time.perf_counter() - t
                self.calls[name] += 1

        return timed


def run_sb3_seed(task: ua.Subtask, steps: int, seed: int, threads: int | None, backend: str = "numpy") -> dict:
    import torch
    from stable_baselines3 import DQN
    from stable_baselines3.common.callbacks import BaseCallback

    if threads:
        torch.set_num_threads(threads)
    watch = Stopwatch()

    class GreedyTests(BaseCallback):
        """One deterministic episode on a separate env every TEST_EVERY training episodes."""

        def __init__(self):
            super().__init__()
            self.env, self.episodes, self.first_optimal, self.tests = ua.SubtaskGymEnv(task), 0, None, []

        def _on_step(self) -> bool:
            if self.locals["dones"][0]:
                self.episodes += 1
                if self.episodes % TEST_EVERY == 0:
                    t = time.perf_counter()
                    obs, _ = self.env.reset()
                    length, terminated, truncated = 0, False, False
                    while not (terminated or truncated):
                        action, _ = self.model.predict(obs, deterministic=True)
                        obs, _, terminated, truncated, _ = self.env.step(action)
                        length += 1
                    self.tests.append(length if terminated else None)
                    if self.first_optimal is None and terminated and length <= task.optimal_steps:
                        self.first_optimal = self.episodes
                    watch.seconds["tests"] = watch.seconds.get("tests", 0.0) + time.perf_counter() - t
            return True

    start = time.perf_counter()
    env = ua.SubtaskGymEnv(task, backend)
    env.step = watch.wrap("env_step", env.step)
    model = DQN("MlpPolicy", env, device="cpu", seed=seed, verbose=0, **sb3_settings(steps))
    model.train = watch.wrap("gradient_steps", model.train)
    model._sample_action = watch.wrap("action_selection", model._sample_action)
    callback = GreedyTests()
    built = time.perf_counter()
    model.learn(total_timesteps=steps, callback=callback)
    wall = time.perf_counter() - start
    assert model.num_timesteps == steps
    tests_s = watch.seconds.get("tests", 0.0)
    learn_s = wall - (built - start)
    other = learn_s - tests_s - sum(watch.seconds[k] for k in ("env_step", "gradient_steps", "action_selection"))
    return {"seed": seed, "wall_s": wall, "build_s": built - start, "learn_s": learn_s, "tests_s": tests_s,
            "train_s": wall - tests_s, "episodes_to_optimal": callback.first_optimal,
            "training_episodes": callback.episodes,
            "split_s": {**{k: v for k, v in watch.seconds.items() if k != "tests"}, "sb3_loop_rest": other},
            "gradient_steps": watch.calls["gradient_steps"], "torch_threads": torch.get_num_threads()}


def median_or_none(xs):
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=8, help="trials: jaxusar runs them in one call, SB3 one after another")
    p.add_argument("--steps", type=int, default=30_000, help="env steps per trial (a multiple of --chunk-steps)")
    p.add_argument("--chunk-steps", type=int, default=10_000, help="jaxusar env steps per jitted chunk")
    p.add_argument("--torch-threads", type=int, default=None, help="torch.set_num_threads (default: torch's own)")
    p.add_argument("--jax-threads", type=int, default=None,
                   help="threads of XLA's CPU intra-op pool (default: one per CPU); 1 runs every op on one thread")
    p.add_argument("--gym-backend", choices=("numpy", "jax"), default="numpy",
                   help="SB3's training env: numpy dynamics, or the package's jitted step called every step")
    p.add_argument("--repeats", type=int, default=3,
                   help="jaxusar runs whose median wall is reported (with --compile-cache: warm runs, after one "
                        "cold run); SB3 runs once")
    p.add_argument("--compile-cache", metavar="DIR",
                   help="JAX's persistent compile cache in DIR, emptied first: the first jaxusar run compiles "
                        "and writes it (cold), the others load their programs from it (warm; the median of those "
                        "is the jaxusar row); ratios are given both ways")
    p.add_argument("--skip-sb3", action="store_true")
    p.add_argument("--out", default="benchmarks/results/vs_sb3.json")
    args = p.parse_args(argv)
    if args.repeats < 1 or (args.jax_threads is not None and args.jax_threads < 1):
        p.error("--repeats and --jax-threads must be >= 1")
    jax_threads = start_xla_cpu(args.jax_threads)
    if args.compile_cache:
        shutil.rmtree(args.compile_cache, ignore_errors=True)
        if enable_compile_cache(folder=args.compile_cache) is None:
            p.error(f"--compile-cache {args.compile_cache}: the folder cannot be written")

    task = ua.navigation_subtask(gamma=MATCHED["gamma"])
    checked = ua.check_gym_matches_jax(task)
    print(f"{ua.SUBTASK} from {task.start}, optimum {task.optimal_steps} steps; Gymnasium adapter == jaxusar "
          f"SubtaskEnv on {checked} random steps")

    runs = args.repeats + bool(args.compile_cache)
    jx_runs = [run_jaxusar(task, args.seeds, args.steps, args.chunk_steps) for _ in range(runs)]
    cold = jx_runs[0] if args.compile_cache else None
    warm = jx_runs[1:] if cold else jx_runs
    jx = sorted(warm, key=lambda r: r["wall_s"])[len(warm) // 2]  # the median run (of an even count, the slower middle one)
    assert all(r["episodes_to_optimal"] == jx["episodes_to_optimal"] for r in jx_runs)  # runs are deterministic
    jx["walls_s"] = [r["wall_s"] for r in jx_runs]
    total = args.seeds * args.steps
    print(f"jaxusar (median of {len(warm)}{' warm' if cold else ''} runs, XLA CPU pool of {jax_threads} thread(s), walls {[round(r['wall_s'], 2) for r in jx_runs]}): {args.seeds} trials x {args.steps} steps in {jx['wall_s']:.2f}s "
          f"(init {jx['init_s']:.2f}s, of which {jx['init_s'] - jx['init_cached_s']:.2f}s compiling; chunk compile "
          f"{jx['compile_s']:.2f}s; run {jx['run_s']:.2f}s, of which the same updates alone take {jx['updates_alone_s']:.2f}s); "
          f"episodes to optimal {jx['episodes_to_optimal']}")
    sb3 = []
    if not args.skip_sb3:
        for s in range(args.seeds):
            r = run_sb3_seed(task, args.steps, s, args.torch_threads, args.gym_backend)
            sb3.append(r)
            print(f"SB3 seed {s}: {r['wall_s']:.1f}s (tests {r['tests_s']:.1f}s), episodes to optimal "
                  f"{r['episodes_to_optimal']}", flush=True)

    rows = {"jaxusar": {"wall_s": jx["wall_s"], "run_s": jx["run_s"], "compile_s": jx["compile_s"],
                        "episodes_to_optimal": jx["episodes_to_optimal"]}}
    rows["jaxusar"].update(us_per_env_step=jx["wall_s"] / total * 1e6, s_per_trial=jx["wall_s"] / args.seeds,
                           steady_us_per_env_step=jx["run_s"] / total * 1e6,
                           median_episodes_to_optimal=median_or_none(jx["episodes_to_optimal"]),
                           trials_optimal=sum(e is not None for e in jx["episodes_to_optimal"]))
    if sb3:
        wall, train = sum(r["wall_s"] for r in sb3), sum(r["train_s"] for r in sb3)
        eto = [r["episodes_to_optimal"] for r in sb3]
        split = {k: sum(r["split_s"][k] for r in sb3) for k in sb3[0]["split_s"]}
        rows["sb3"] = {"wall_s": wall, "train_s": train, "tests_s": wall - train, "us_per_env_step": wall / total * 1e6,
                       "train_us_per_env_step": train / total * 1e6, "s_per_trial": wall / args.seeds,
                       "episodes_to_optimal": eto, "median_episodes_to_optimal": median_or_none(eto),
                       "trials_optimal": sum(e is not None for e in eto),
                       "split_us_per_env_step": {k: v / total * 1e6 for k, v in split.items()},
                       "build_s": sum(r["build_s"] for r in sb3)}
        rows["ratio"] = {"sb3_wall_over_jaxusar_wall": wall / jx["wall_s"],
                         "sb3_train_over_jaxusar_wall": train / jx["wall_s"],
                         "sb3_train_over_jaxusar_run": train / jx["run_s"]}
        if cold:
            rows["ratio"]["sb3_wall_over_jaxusar_cold_wall"] = wall / cold["wall_s"]
    if cold:
        rows["jaxusar_cold"] = {"wall_s": cold["wall_s"], "run_s": cold["run_s"], "compile_s": cold["compile_s"],
                                "init_s": cold["init_s"], "us_per_env_step": cold["wall_s"] / total * 1e6,
                                "s_per_trial": cold["wall_s"] / args.seeds,
                                "median_episodes_to_optimal": median_or_none(cold["episodes_to_optimal"]),
                                "trials_optimal": sum(e is not None for e in cold["episodes_to_optimal"])}

    import torch
    import stable_baselines3

    env_info = {**environment_info(), "torch": torch.__version__, "stable_baselines3": stable_baselines3.__version__,
                "torch_threads": sb3[0]["torch_threads"] if sb3 else None, "jax_threads": jax_threads}
    result = {"task": ua.SUBTASK, "start": task.start, "optimal_steps": task.optimal_steps, "seeds": args.seeds,
              "env_steps_per_trial": args.steps, "test_every": TEST_EVERY, "gym_backend": args.gym_backend,
              "jaxusar_repeats": len(warm), "compile_cache": bool(args.compile_cache), "matched": MATCHED,
              "sb3_settings": {k: v for k, v in sb3_settings(args.steps).items()}, "summary": rows,
              "jaxusar": jx, "sb3": sb3, "environment": env_info}
    print()
    print(f"{args.seeds} trials x {args.steps} env steps, hidden {MATCHED['hidden']}, batch {MATCHED['batch_size']}, "
          f"update every {MATCHED['train_every']} steps")
    print(f"{'':12} {'wall s':>8} {'s/trial':>8} {'us/env step':>12} {'median eps to opt':>18} {'trials optimal':>15}")
    for name, r in rows.items():
        if name == "ratio":
            continue
        print(f"{name:12} {r['wall_s']:8.1f} {r['s_per_trial']:8.2f} {r['us_per_env_step']:12.1f} "
              f"{str(r['median_episodes_to_optimal']):>18} {r['trials_optimal']:>12}/{args.seeds}")
    if sb3:
        ra = rows["ratio"]
        print(f"ratio SB3 / jaxusar wall: {ra['sb3_wall_over_jaxusar_wall']:.1f}x (SB3 without its tests: "
              f"{ra['sb3_train_over_jaxusar_wall']:.1f}x; vs jaxusar without compile: {ra['sb3_train_over_jaxusar_run']:.1f}x)"
              + (f"; against jaxusar's cold run: {ra['sb3_wall_over_jaxusar_cold_wall']:.1f}x" if cold else ""))
        print("SB3 us per env step: " + ", ".join(f"{k} {v:.0f}" for k, v in rows["sb3"]["split_us_per_env_step"].items()))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2, default=float))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.exit(main())
