"""jaxusar IQL vs JaxMARL-style IQL on the two-agent task, side by side in one run (issue 7).

Both sides: the two-rooms map, both medics, team reward (+100 per triage), horizon 300; jaxusar's
IQL settings (``configs/iql.yaml``: 32x32 MLP per agent, batch 32, buffer 50k, one update per 8 env
steps, target copy every 250 updates, epsilon 1.0 -> 0.05 over 50k env steps, Adam 5e-4, Huber,
gradient clipping 10, gamma 0.99, learning from env step 1000); the same env steps per trial; all
trials in one call on each side; a greedy test every 50 training episodes.

* jaxusar: ``jaxusar.experiments.train.build`` (IQL) -> ``Trainer``, chunks run to the step budget.
* JaxMARL: ``benchmarks/jaxmarl_iql.py`` (JaxMARL's IQL structure on jaxmarl's ``CTRolloutManager``
  and flashbax; see its docstring for what it is and is not) on the package's JaxMARL adapter,
  ``jaxusar.interop.JaxMARLEnv`` (agents ``agent_0``, ``agent_1``; each sees the full 60-float
  observation, as jaxusar's IQL learners do; the team reward goes to both; JaxMARL's auto-reset),
  ``jax.jit(jax.vmap(train))(rngs)``, with parameter sharing (JaxMARL's default) and without.

Wall time = compile + run on both sides (jaxusar: + ``Trainer.init``; its ``build``, which runs the
BFS planner for the optimum, is timed apart as ``setup_s``; the JaxMARL side is given that optimum, 18). Where the time goes: each side once more with its gradient
updates switched off (jaxusar: ``learning_starts`` past the budget; JaxMARL: ``NUM_MINI_EPOCHS=0``),
so that updates = full - no-updates.

    python benchmarks/vs_jaxmarl.py                                 # 8 trials x 300k env steps
    python benchmarks/vs_jaxmarl.py --seeds 2 --steps 40000 --no-breakdown   # smoke run
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

import jaxmarl_iql as jm
from jaxusar import config, envs
from jaxusar.experiments.train import build, environment_info
from jaxusar.interop import JaxMARLEnv

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "iql.yaml"
OPTIMAL_TEAM_STEPS = 18


def jaxusar_cfg(steps: int, chunk_steps: int, updates: bool = True):
    sets = [f"train.episodes={steps // OPTIMAL_TEAM_STEPS + 1}", f"train.chunk_steps={chunk_steps}"]
    if not updates:
        sets.append(f"dqn.learning_starts={steps + 1}")
    return config.load(CONFIG, sets)


def matched_jaxmarl(cfg, steps: int, sharing: bool, updates: bool = True) -> dict:
    d = cfg.dqn
    return dict(NUM_ENVS=1, NUM_STEPS=d.train_every, TOTAL_TIMESTEPS=steps, BUFFER_SIZE=d.buffer_capacity,
                BUFFER_BATCH_SIZE=d.batch_size, HIDDEN=tuple(d.hidden), EPS_START=d.eps_start, EPS_FINISH=d.eps_end,
                EPS_DECAY=d.eps_decay_steps / steps, MAX_GRAD_NORM=d.max_grad_norm,
                TARGET_UPDATE_INTERVAL=d.target_update_every, TAU=d.tau, NUM_MINI_EPOCHS=1 if updates else 0,
                LR=d.lr, OPTIMIZER="adam", LOSS=d.loss, LEARNING_STARTS=d.learning_starts, GAMMA=d.gamma,
                PARAMETER_SHARING=sharing, TEST_EVERY_EPISODES=cfg.train.test_every,
                OPTIMAL_STEPS=OPTIMAL_TEAM_STEPS, MIN_EPISODE_STEPS=OPTIMAL_TEAM_STEPS)


def first_triage(results: dict, every: int) -> list:
    out = []
    for row in np.asarray(results["test_return"]):
        hit = np.flatnonzero(row > 0)
        out.append(int((hit[0] + 1) * every) if len(hit) else None)
    return out


def run_jaxusar(cfg, seeds: int, steps: int) -> dict:
    t = time.perf_counter()
    _, reference, _, trainer = build(cfg)  # runs the planner (the optimum); timed apart, not in wall_s
    optimal = reference["steps"]
    setup_s = time.perf_counter() - t
    assert optimal == OPTIMAL_TEAM_STEPS
    start = time.perf_counter()
    if steps % trainer.chunk_steps:
        raise SystemExit(f"--steps {steps} must be a multiple of the chunk ({trainer.chunk_steps} env steps)")
    state = trainer.init(jax.random.split(jax.random.PRNGKey(0), seeds))
    jax.block_until_ready(state)
    init_s = time.perf_counter() - start
    compile_s = trainer.compile(state)
    t = time.perf_counter()
    for _ in range(steps // trainer.chunk_steps):
        state = trainer.run_chunk(state)
    jax.block_until_ready(state)
    run_s = time.perf_counter() - t
    res = trainer.results(state)
    return {"wall_s": time.perf_counter() - start, "setup_s": setup_s, "init_s": init_s, "compile_s": compile_s,
            "run_s": run_s, "episodes_to_optimal": res["episodes_to_optimal"], "episodes_to_solved": res["episodes_to_solved"],
            "episodes_to_first_triage": first_triage(res, cfg.train.test_every),
            "training_episodes": np.asarray(state.trials.episodes).tolist()}


def run_jaxmarl(config_dict: dict, seeds: int) -> dict:
    start = time.perf_counter()
    env = JaxMARLEnv(envs.make("two_rooms", horizon=300))
    train = jax.jit(jax.vmap(jm.make_train(config_dict, env)))
    rngs = jax.random.split(jax.random.PRNGKey(0), seeds)
    compiled = train.lower(rngs).compile()
    compile_s = time.perf_counter() - start
    t = time.perf_counter()
    out = jax.block_until_ready(compiled(rngs))
    run_s = time.perf_counter() - t
    eto = jm.episodes_to(out, config_dict["TEST_EVERY_EPISODES"], OPTIMAL_TEAM_STEPS)
    return {"wall_s": time.perf_counter() - start, "compile_s": compile_s, "run_s": run_s,
            "episodes_to_optimal": eto["optimal"], "episodes_to_first_triage": eto["first_triage"],
            "training_episodes": np.asarray(out["episodes"]).tolist(),
            "tests_abandoned": np.asarray(out["tests_abandoned"]).tolist(),
            "grad_steps": np.asarray(out["grad_steps"]).tolist()}


def med(xs):
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--steps", type=int, default=300_000, help="env steps per trial (a multiple of --chunk-steps)")
    p.add_argument("--chunk-steps", type=int, default=20_000, help="jaxusar env steps per jitted chunk")
    p.add_argument("--repeats", type=int, default=1, help="timed runs per setup (medians reported), order rotated")
    p.add_argument("--no-breakdown", action="store_true", help="skip the runs with updates switched off")
    p.add_argument("--out", default="benchmarks/results/vs_jaxmarl.json")
    args = p.parse_args(argv)

    args.chunk_steps = min(args.chunk_steps, args.steps)
    cfg = jaxusar_cfg(args.steps, args.chunk_steps)
    setups = {
        "jaxusar": lambda: run_jaxusar(cfg, args.seeds, args.steps),
        "jaxmarl_ps": lambda: run_jaxmarl(matched_jaxmarl(cfg, args.steps, True), args.seeds),
        "jaxmarl_ns": lambda: run_jaxmarl(matched_jaxmarl(cfg, args.steps, False), args.seeds),
    }
    if not args.no_breakdown:
        setups.update({
            "jaxusar_no_updates": lambda: run_jaxusar(jaxusar_cfg(args.steps, args.chunk_steps, False), args.seeds,
                                                      args.steps),
            "jaxmarl_ps_no_updates": lambda: run_jaxmarl(matched_jaxmarl(cfg, args.steps, True, False), args.seeds),
            "jaxmarl_ns_no_updates": lambda: run_jaxmarl(matched_jaxmarl(cfg, args.steps, False, False), args.seeds),
        })
    runs = {name: [] for name in setups}
    names = list(setups)
    for r in range(args.repeats):
        for name in names[r % len(names):] + names[:r % len(names)]:
            out = setups[name]()
            runs[name].append(out)
            print(f"[{r}] {name:22} wall {out['wall_s']:6.1f}s (compile {out['compile_s']:.1f}s, run {out['run_s']:.1f}s); "
                  f"episodes to optimal {out['episodes_to_optimal']}; to first triage {out['episodes_to_first_triage']}",
                  flush=True)

    total = args.seeds * args.steps
    summary = {}
    for name, rs in runs.items():
        wall, run = statistics.median(r["wall_s"] for r in rs), statistics.median(r["run_s"] for r in rs)
        summary[name] = {"wall_s": wall, "run_s": run, "compile_s": statistics.median(r["compile_s"] for r in rs),
                         "us_per_env_step": wall / total * 1e6, "s_per_trial": wall / args.seeds,
                         "env_steps_per_s": total / wall, "run_env_steps_per_s": total / run,
                         "median_episodes_to_optimal": med(rs[0]["episodes_to_optimal"]),
                         "trials_optimal": sum(e is not None for e in rs[0]["episodes_to_optimal"]),
                         "median_episodes_to_first_triage": med(rs[0]["episodes_to_first_triage"]),
                         "trials_triaging": sum(e is not None for e in rs[0]["episodes_to_first_triage"])}
    for name in ("jaxmarl_ps", "jaxmarl_ns"):
        summary[name]["jaxusar_speedup_wall"] = summary[name]["wall_s"] / summary["jaxusar"]["wall_s"]
        summary[name]["jaxusar_speedup_run"] = summary[name]["run_s"] / summary["jaxusar"]["run_s"]
    if not args.no_breakdown:
        for name in ("jaxusar", "jaxmarl_ps", "jaxmarl_ns"):
            s, n = summary[name], summary[f"{name}_no_updates"]
            s["run_s_without_updates"] = n["run_s"]
            s["run_s_updates"] = s["run_s"] - n["run_s"]
            s["us_per_update"] = s["run_s_updates"] / (args.seeds * args.steps / cfg.dqn.train_every) * 1e6

    import flashbax
    import jaxmarl

    result = {"seeds": args.seeds, "env_steps_per_trial": args.steps, "repeats": args.repeats,
              "jaxusar_config": cfg.to_dict(), "jaxmarl_config": matched_jaxmarl(cfg, args.steps, True),
              "summary": summary, "runs": runs,
              "environment": {**environment_info(), "jaxmarl": getattr(jaxmarl, "__version__", "0.2.0"),
                              "flashbax": getattr(flashbax, "__version__", "0.1.3")}}
    print()
    print(f"{args.seeds} trials x {args.steps} env steps, IQL, hidden {list(cfg.dqn.hidden)}, batch {cfg.dqn.batch_size}, "
          f"update every {cfg.dqn.train_every} env steps; medians of {args.repeats} run(s)")
    print(f"{'':22} {'wall s':>7} {'compile s':>9} {'run s':>7} {'s/trial':>8} {'us/env step':>11} "
          f"{'eps to optimal':>14} {'eps to 1st triage':>17}")
    for name, s in summary.items():
        print(f"{name:22} {s['wall_s']:7.1f} {s['compile_s']:9.1f} {s['run_s']:7.1f} {s['s_per_trial']:8.2f} "
              f"{s['us_per_env_step']:11.2f} {str(s['median_episodes_to_optimal']):>14} "
              f"{str(s['median_episodes_to_first_triage']) + ' (' + str(s['trials_triaging']) + '/' + str(args.seeds) + ')':>17}")
    for name in ("jaxmarl_ps", "jaxmarl_ns"):
        s = summary[name]
        print(f"jaxusar speed-up over {name}: {s['jaxusar_speedup_wall']:.2f}x wall, {s['jaxusar_speedup_run']:.2f}x run")
    if not args.no_breakdown:
        for name in ("jaxusar", "jaxmarl_ps", "jaxmarl_ns"):
            s = summary[name]
            print(f"{name}: run {s['run_s']:.1f}s = updates {s['run_s_updates']:.1f}s ({s['us_per_update']:.1f} us per "
                  f"update per trial) + the rest {s['run_s_without_updates']:.1f}s")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2, default=float))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.exit(main())
