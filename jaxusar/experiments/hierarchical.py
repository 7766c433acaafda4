"""The paper's method end to end: sub-policies (all tasks x trials, one vmapped call), then the
coordinator (all trials, one vmapped call) on each trial's best sub-policies.

Output folder::

    metrics.json          episodes_to_optimal per trial (= sub-policy sum + coordinator, as Table II counts
                          them), the two parts, the per-task counts, the max over tasks (they train
                          concurrently), compile and run seconds per stage, config, versions
    curves.csv            stage (subpolicy|coordinator), task, trial, kind, episode, return, steps, optimal,
                          start_optimal (the test episode from its start), coverage (sub-policies: the
                          fraction of initiation states from which the greedy policy is optimal)
    fig4_subpolicies.png  train and test steps per task (paper Fig. 4), band over trials, 8 tasks a page
                          (fig4_subpolicies_2.png, ... past 8); and
    fig4_<task>.png       the same for each sub-policy alone
    coordinator.png       the coordinator's train and test curves
    team_episode.png      the best trial's greedy team episode, as a strip of frames
    params/               best sub-policy and coordinator params per trial
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from jaxusar import envs, planning
from jaxusar.algos import coordinator as coord
from jaxusar.algos import subpolicies as sp
from jaxusar.algos.options import NAVIGATE, TRIAGE, check_option_kinds, method_env, options_from_graph
from jaxusar.config import ConfigError, ExperimentConfig, TrainConfig
from jaxusar.core import Trainer
from jaxusar.experiments import scripted as sc
from jaxusar.experiments.plots import band, band_key, kept, reward_range, smooth, training_figure
from jaxusar.experiments.runner import Stage
from jaxusar.experiments.stats import in_words, summarize
from jaxusar.experiments.train import environment_info, reference_metrics, stage_seconds

PAGE_TASKS = 8  # sub-policies per page of fig4_subpolicies*.png (office has 23: three pages, not one of 69 panels)
TITLE_PLAN_CHARS = 160  # team_episode.png lists the coordinator's decisions in its title up to this length


def build(cfg: ExperimentConfig):
    """Everything the two stages need. The coordinator's macro env runs its sub-policies as tables of
    actions: ``coordinator_params(sub_params, batch_dims)`` tabulates trained ones' greedy actions
    (``sp.greedy_tables``); ``coord.CoordinatorParams(subpolicy=sp.exact_subpolicies(...))`` runs exact ones."""
    world, env, options = setup(cfg)
    h, c = cfg.hierarchical, cfg.hierarchical.coordinator
    tasks = sp.make_tasks(env, options, h.triage_start, h.navigate_start, h.navigation)
    params = sp.task_params(env, tasks, cfg.dqn.gamma, cfg.hierarchical.task_gamma)
    n_goals = max(len(t.goals or t.targets) for t in tasks)  # goal-conditioned tasks: their goals; else 0
    senv = sp.SubtaskEnv(env, env.horizon, h.subpolicy_features, n_goals, h.focus_starts)
    sub_learner = sp.make_learner(senv, cfg.dqn)
    # fewest steps of any training episode: from any start (0 would mean a start inside the goal)
    min_steps = int(min(params.dist[k, s[:, 3], s[:, 0], s[:, 1], s[:, 2]].min() for k, s in
                        enumerate(t.starts for t in tasks)))
    sub_train = dataclasses.replace(cfg.train, test_draws=1)  # sub-tasks draw nothing; coverage judges them
    sub_trainer = Trainer(senv, sub_learner, sub_train, learning_starts=cfg.dqn.learning_starts,
                          train_every=cfg.dqn.train_every, gradient_steps=cfg.dqn.gradient_steps, optimal_steps=0,
                          min_episode_steps=max(min_steps, 1))
    table = sp.policy_table(env, options, tasks, h.navigation)
    check_rooms_reachable(env, options, table, h.navigation)
    macro = coord.MacroEnv(env, options, table,
                           subpolicy_act=sp.table_act(senv),
                           observe=senv.observe, gamma=c.gamma, invalid_penalty=c.invalid_penalty,
                           option_timeout=c.option_timeout or auto_option_timeout(env, options, tasks, params),
                           factored=c.kind == "factored", block_patience=c.block_patience,
                           dodge=c.dodge, cells=c.features == "cells", own_termination=c.termination == "own",
                           option_goals=sp.option_goals(options, tasks), **slot_tables(options, tasks, params))
    coord_learner = coord.make_learner(macro, c)
    # the coordinator's chunks take a second or two, less than compiling a smaller batch's program: its
    # stopped trials stay in the batch (masked) and the stage ends once every trial has stopped
    # (benchmarks/README.md, "The coordinator's cost"; the same results either way)
    coord_train = TrainConfig(episodes=c.episodes, test_every=c.test_every, chunk_steps=c.chunk_steps,
                              optimal_slack=cfg.train.optimal_slack, stop_at_optimal=c.stop_at_optimal,
                              test_draws=cfg.train.test_draws, drop_finished=False)
    reference = planning.team_reference(world)
    optimal = reference["steps"]
    coord_trainer = Trainer(macro, coord_learner, coord_train, learning_starts=c.learning_starts, train_every=1,
                            gradient_steps=c.gradient_steps, optimal_steps=optimal, min_episode_steps=1,
                            test_horizon=env.horizon)
    coordinator_params = lambda sub, batch_dims=2: coord.CoordinatorParams(subpolicy=sp.greedy_tables(
        senv, sub_learner, sub, params.dist.shape[1], batch_dims))  # [trial, task, ...] params by default
    return dict(env=env, options=options, tasks=tasks, task_params=params, subtask_env=senv, sub_learner=sub_learner,
                sub_trainer=sub_trainer, macro=macro, coord_learner=coord_learner, coord_trainer=coord_trainer,
                optimal=optimal, reference=reference, coordinator_params=coordinator_params)


def slot_tables(options, tasks, params) -> dict:
    """Where victims are drawn (``options.slot_flag``), what ``MacroEnv`` needs to run TRIAGE-IN-R one
    slot at a time: ``slot_task`` and ``slot_goal`` int32[S] (the room's task, and the slot's goal index in
    it), ``slot_dist`` (the slot's distance table, per rubble mode) and ``slot_every_mode`` (its task runs
    in the rubble's mode, else in mode 0: ``Task.every_mode``); else nothing."""
    if options.slot_flag is None:
        return {}
    n = len(options.slot_flag)
    task, goal, every_mode = np.full(n, -1, np.int32), np.zeros(n, np.int32), np.ones(n, bool)
    for k, t in enumerate(tasks):
        for g, v in enumerate(t.targets):
            task[v], goal[v], every_mode[v] = k, g, t.every_mode
    modes = params.dist.shape[1] // params.goal_region.shape[1]
    dist = np.stack([np.asarray(params.dist[k][g * modes:(g + 1) * modes]) for k, g in zip(task, goal)])
    return {"slot_task": task, "slot_goal": goal, "slot_dist": dist, "slot_every_mode": every_mode}


def setup(cfg: ExperimentConfig):
    """(the map's env, the method's env, its options) for ``cfg``; a one-line ConfigError, before anything
    compiles, where the method cannot run as configured: option kinds the map cannot offer, or a flat
    coordinator past ``max_joint_options``. The method's env is the same world with rubble in a doorway
    counted as the hall's (``options.method_env``). Every rule of the contract is mastered: rubble and
    engineers (CLEAR), victims drawn at reset, multi-step triage, expiry and "view" (TRIAGE-IN-R works slot
    by slot and searches; the coordinator's abstract state holds only what the team has seen)."""
    world = envs.make(cfg.env.map, **cfg.env.overrides())
    h, c = cfg.hierarchical, cfg.hierarchical.coordinator
    check_option_kinds(h.option_kinds, world)
    env = method_env(world)
    options = options_from_graph(env.graph, h.navigation, env, h.option_kinds)
    if c.kind == "flat" and options.n ** env.n_agents > c.max_joint_options:
        raise ConfigError(f"the flat coordinator on {env.layout.name!r} would choose among "
                          f"{options.n ** env.n_agents:,} joint options ({options.n} options ^ {env.n_agents} agents), "
                          f"more than hierarchical.coordinator.max_joint_options={c.max_joint_options:,}; use the "
                          "factored coordinator (--set hierarchical.coordinator.kind=factored), linear in the agents")
    return world, env, options


def check_rooms_reachable(env, options, table: np.ndarray, navigation: str) -> None:
    """Every victim's room is some medic's start region or has a NAVIGATE sub-policy in ``table``
    (``sp.policy_table``); else a ConfigError names the room (adjacent navigation on a map with rooms
    beyond the medics' neighbours)."""
    start_region = env.graph.cell_region[tuple(env.layout.agent_start.T)]
    for o in np.flatnonzero(options.kind == TRIAGE):
        room = options.region[o]
        nav = np.flatnonzero((options.kind == NAVIGATE) & (options.region == room))
        if not ((start_region == room).any() or (table[:, :, nav] >= 0).any()):
            raise ConfigError(f"no medic on {env.layout.name!r} can reach {env.graph.names[room]!r} for "
                              f"{options.names[o]} with hierarchical.navigation={navigation} (sub-policies only to "
                              "rooms next to a medic's start); use hierarchical.navigation=chained")


def auto_option_timeout(env, options, tasks, params) -> int:
    """``coordinator.option_timeout: 0``: 1.5x the longest shortest path of any option from any state it
    may start in (a chained NAVIGATE across the map included), at least 50 steps (two_rooms: 50)."""
    longest, region, modes = 0, env.graph.cell_region, len(params.dist[0]) // len(params.goal_region[0])
    # where victims are drawn, TRIAGE-IN-R visits its room's slots one after another
    for k, t in enumerate(tasks):
        if t.victim >= 0 or t.targets or t.clears:
            steps = int(params.dist[k][tuple(t.initiation[:, [3, 0, 1, 2]].T)].max())
            longest = max(longest, steps * max(len(t.targets), 1))
        elif t.option >= 0 or t.goals:  # a NAVIGATE option's task: its table is the room's distance from anywhere
            for g, room in enumerate(t.goal_regions):
                starts = options.starts_from[np.maximum(region, 0), room] & (region >= 0)
                longest = max(longest, int(params.dist[k][g * modes:(g + 1) * modes][:, starts].max()))
    return max(50, -(-3 * longest // 2))


def team_episode(macro: coord.MacroEnv, learner, coord_params, subpolicy, key=None):
    """The greedy coordinator's team episode over one trial's sub-policy tables, primitive step by
    primitive step (for pictures); ``key``: the reset's (default: the first judging draw,
    ``scripted.judging_keys``)."""
    p = coord.CoordinatorParams(subpolicy=subpolicy)
    decide = jax.jit(lambda obs: macro.options_of(learner.greedy_act(coord_params, obs, None)[0]))
    info = jax.jit(lambda obs: (macro.available(*macro.decode(obs)).any(-1), macro.valid_options(obs)))
    advance = jax.jit(lambda s, o, a, b: macro.advance(s, o, a, b, p))
    over = jax.jit(macro.option_over)
    settle = jax.jit(macro.still_running)
    obs, ms = macro.reset(sc.judging_keys(macro.env)[0] if key is None else key)
    s = ms.env
    states, rewards, decisions = [s], [], []
    done = False
    while not done:
        options = decide(obs)
        active, valid_options = info(obs)
        valid = bool(valid_options[np.arange(macro.n_agents), np.asarray(options)].all())
        decisions.append([macro.options.names[o] for o in np.asarray(options)] + [valid])
        if not valid:
            s = s.replace(t=s.t + 1)
            states.append(s), rewards.append(macro.invalid_penalty)
            done = int(s.t) >= macro.horizon
            ms = ms.replace(env=s)
        else:
            k, blocked = 0, macro.unblocked()
            while True:
                s, r, d, blocked = advance(s, options, active, blocked)
                states.append(s), rewards.append(float(r))
                k, done = k + 1, bool(d)
                if done or bool(over(s, options, active, blocked, ms.elapsed + k)):
                    break
            running, elapsed = settle(ms, s, options, active, blocked, k)
            ms = coord.MacroState(env=s, running=running, elapsed=elapsed)
        obs = macro.observe(ms)
    return states, np.asarray(rewards, np.float32), decisions


def subpolicy_figure(results: dict, names: list[str], path: Path, horizon: int, optimal: np.ndarray,
                     title: str | None = None):
    """Paper Fig. 4: per task, train steps (moving average) and test steps vs episodes, band over trials,
    and beside them the fraction of the option's initiation states from which the greedy policy is optimal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(names)
    fig, axes = plt.subplots(n, 3, figsize=(15, 2.4 * n), squeeze=False)
    for k, name in enumerate(names):
        tl, tel = results["train_length"][k], results["test_length"][k]  # [trials, episodes]
        band(axes[k, 0], np.arange(1, tl.shape[1] + 1), smooth(tl, 10))
        band(axes[k, 1], results["test_episode"], kept(tel, results["best_length"][k]))
        band(axes[k, 2], results["test_episode"], 100 * kept(results["test_coverage"][k], results["best_coverage"][k]),
             color="tab:purple")
        for ax, what in zip(axes[k, :2], ("train steps (moving avg 10)", "greedy test steps (from the start)")):
            ax.axhline(horizon, color="grey", ls=":", lw=1)
            if optimal[k] >= 0:
                ax.axhline(optimal[k], color="green", ls="--", lw=1)
            ax.set_title(f"{name}: {what}", fontsize=9)
            ax.set_ylim(0, horizon * 1.05)
            ax.set_ylabel("steps")
        axes[k, 2].set_title(f"{name}: initiation states optimal", fontsize=9)
        axes[k, 2].set_ylim(0, 102)
        axes[k, 2].axhline(100, color="green", ls="--", lw=1)
        axes[k, 2].set_ylabel("% of states")
        for ax in axes[k]:
            ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("training episodes")
    from matplotlib.lines import Line2D

    band_key(fig, tl.shape[0], extra={
        "optimal (shortest path; 100% of states)": Line2D([], [], color="green", ls="--", lw=1),
        "horizon (episode cap)": Line2D([], [], color="grey", ls=":", lw=1)})
    fig.suptitle(title or "Sub-policies on pseudo-rewards (paper Fig. 4); right: the % of the option's initiation "
                 "states from which the greedy policy takes a shortest path", fontsize=10)
    # the key and the title keep fixed heights (a fraction of a tall figure left the title over the first row)
    fig.tight_layout(rect=(0, 0.6 / (2.4 * n), 1, 1 - 0.45 / (2.4 * n)))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def subpolicy_pages(results: dict, names: list[str], out: Path, horizon: int, optimal: np.ndarray) -> list[Path]:
    """``subpolicy_figure`` of every task, ``PAGE_TASKS`` per page: ``fig4_subpolicies.png``, then
    ``fig4_subpolicies_2.png``, ... Returns the pages' paths."""
    pages = [list(range(k, min(k + PAGE_TASKS, len(names)))) for k in range(0, len(names), PAGE_TASKS)]
    paths = []
    for p, tasks in enumerate(pages):
        page = {n: (v if n == "test_episode" else np.asarray(v)[tasks]) for n, v in results.items()
                if n in ("train_length", "test_length", "test_coverage", "best_length", "best_coverage", "test_episode")}
        path = out / ("fig4_subpolicies.png" if p == 0 else f"fig4_subpolicies_{p + 1}.png")
        title = None if len(pages) == 1 else (
            f"Sub-policies on pseudo-rewards (paper Fig. 4), page {p + 1} of {len(pages)}: {tasks[0] + 1}-{tasks[-1] + 1} "
            f"of {len(names)}; right: the % of the initiation states from which the greedy policy is optimal")
        subpolicy_figure(page, [names[k] for k in tasks], path, horizon, np.asarray(optimal)[tasks], title)
        paths.append(path)
    return paths


def summary_lines(metrics: dict, per_subpolicy: int, coordinator: int) -> list[str]:
    """What the console says at the end of a run, from its metrics: what the budget is made of, how many
    sub-policies are exact from every state, the best greedy team episode against the reference, then the
    counts of episodes to optimal (the coordinator's alone; end to end, which needs both).

    Trial by trial up to 8 trials, summed up past that."""
    tasks, trials, ref = metrics["tasks"], metrics["trials"], metrics["optimal_team_steps"]
    n, by_trial = len(tasks), trials <= 8
    budget = n * per_subpolicy + coordinator
    lines = [f"budget per trial: {n} sub-policies x {per_subpolicy:,} episodes + {coordinator:,} coordinator "
             f"episodes = {budget:,} episodes"]

    per_task = metrics["subpolicy_episodes_to_optimal"]["per_task"]
    exact = [sum(per_task[t][j] is not None for t in tasks) for j in range(trials)]
    text = (", ".join(f"trial {j}: {e}/{n}" for j, e in enumerate(exact)) if by_trial else
            f"all {n} in {sum(e == n for e in exact)} of {trials} trials, fewest {min(exact)}/{n}")
    coverage = metrics["subpolicy_coverage"]
    misses = [(coverage[t][j], t, j) for t in tasks for j in range(trials) if per_task[t][j] is None]
    if misses:
        c, t, j = min(misses)
        text += (f"; the least: {t} in trial {j}, optimal from {c:.1%} of its "
                 f"{metrics['subpolicy_initiation_states'][t]:,} states")
    lines.append(f"sub-policies greedy-optimal from every state they may start in: {text}")

    exact_ref = metrics["reference"] == "optimum"
    what = (f"the optimum is {ref} steps (exact joint search)" if exact_ref else
            f"the lower bound is {ref} steps (the exact optimum is out of the search's reach; a team at the bound "
            "is optimal)")
    steps, gaps = metrics["best_team_test_steps"], metrics["optimality_gap"]
    if by_trial:
        teams = ", ".join(f"trial {j}: " + (f"{s} steps" if g is not None else "no test triaged every victim")
                          for j, (s, g) in enumerate(zip(steps, gaps)))
    else:
        solved = [s for s, g in zip(steps, gaps) if g is not None]
        teams = (f"every victim triaged in {len(solved)} of {trials} trials"
                 + (f", in {min(solved)} to {max(solved)} steps (median {np.median(solved):g})" if solved else ""))
    at = sum(g is not None and s <= ref for s, g in zip(steps, gaps))
    lines.append(f"best greedy team episode (the coordinator over its trial's sub-policies): {teams}; {what}; "
                 f"{at} of {trials} trials at it")

    lines.append(f"the coordinator alone (its team episode at the {'optimum' if exact_ref else 'bound'}, "
                 f"whatever its sub-policies): {in_words(metrics['coordinator_episodes_to_optimal'], coordinator)}")
    lines.append("end to end, as Table II counts (every sub-policy exact from every state, then the coordinator): "
                 f"{in_words(metrics['episodes_to_optimal'], budget)}")
    lines.append("the same with each sub-policy judged by the paper's single-start test: "
                 f"{in_words(metrics['episodes_to_optimal_single_start'], budget)}")
    return lines


class Experiment:
    """Two stages in one chain: the sub-policies (lanes ordered [trial, task], one vmapped call), then
    the coordinator (one lane per trial) over each trial's best sub-policy params."""

    FIGURES = ("fig4_subpolicies.png (_2, _3, ...: 8 sub-policies a page)", "fig4_<task>.png", "coordinator.png",
               "team_episode.png")

    def __init__(self, cfg: ExperimentConfig, keys: jax.Array):
        self.cfg, self.trials = cfg, len(keys)
        self.b = b = build(cfg)
        n_tasks = len(b["tasks"])
        lane_keys = jax.vmap(lambda k: jax.vmap(lambda t: jax.random.fold_in(k, t))(jnp.arange(n_tasks)))(keys)
        lane_params = jax.tree.map(lambda x: jnp.tile(jnp.asarray(x), (self.trials,) + (1,) * (x.ndim - 1)),
                                   b["task_params"])
        self.chains = [[
            Stage("hierarchical/subpolicies", b["sub_trainer"], lane_keys.reshape(-1, *keys.shape[1:]), lane_params),
            Stage("hierarchical/coordinator", b["coord_trainer"], keys,
                  lambda sub: b["coordinator_params"](self._by_trial(sub.results["best_params"]))),
        ]]

    def _by_trial(self, lanes):
        """A leading [trial * task] lanes axis as [trial, task]."""
        n_tasks = len(self.b["tasks"])
        return jax.tree.map(lambda a: jnp.asarray(a).reshape(-1, n_tasks, *np.shape(a)[1:]), lanes)

    def finish(self, out: Path, outcomes: dict, figures: bool = True) -> dict:
        b, cfg, tasks = self.b, self.cfg, self.b["tasks"]
        n_tasks = len(tasks)
        sub_o, co_o = outcomes["hierarchical/subpolicies"], outcomes["hierarchical/coordinator"]
        sub, co = dict(sub_o.results), co_o.results
        trials = co["train_return"].shape[0]
        eto_lanes, test_episode = sub.pop("episodes_to_optimal"), sub.pop("test_episode")
        start_lanes = sub.pop("episodes_to_start_optimal")
        sub.pop("episodes_to_solved")
        best_sub = self._by_trial(sub["best_params"])  # [trial, task, ...]
        sub = {**jax.tree.map(lambda a: np.swapaxes(np.asarray(self._by_trial(a)), 0, 1), sub),
               "test_episode": test_episode}  # [task, trial, ...]
        by_task = lambda lanes: [[lanes[j * n_tasks + k] for j in range(trials)] for k in range(n_tasks)]
        sub_eto, sub_start = by_task(eto_lanes), by_task(start_lanes)

        per_trial = []
        for j in range(trials):
            parts = [sub_eto[k][j] for k in range(n_tasks)]
            sub_sum = None if None in parts else int(sum(parts))
            sub_max = None if None in parts else int(max(parts))
            c_eto = co["episodes_to_optimal"][j]
            total = None if sub_sum is None or c_eto is None else sub_sum + c_eto
            starts = [sub_start[k][j] for k in range(n_tasks)]
            single = None if None in starts or c_eto is None else int(sum(starts)) + c_eto
            per_trial.append({"subpolicies_sum": sub_sum, "subpolicies_max": sub_max, "coordinator": c_eto,
                              "total": total, "single_start_total": single})
        eto = [p["total"] for p in per_trial]
        sub_steps = np.asarray(sub["env_steps"]).sum(0)  # per trial, over its sub-policies' lanes
        metrics = {
            "algorithm": "hierarchical", "trials": trials, "episodes_to_optimal": eto, **summarize(eto),
            "subpolicy_episodes_to_optimal": {"sum": [p["subpolicies_sum"] for p in per_trial],
                                              "max": [p["subpolicies_max"] for p in per_trial],
                                              "per_task": {t.name: sub_eto[k] for k, t in enumerate(tasks)}},
            # the paper's single-start test: the greedy episode from the test start takes the shortest path
            "subpolicy_episodes_to_start_optimal": {t.name: sub_start[k] for k, t in enumerate(tasks)},
            # the kept params: the fraction of the option's initiation states from which they are optimal
            "subpolicy_coverage": {t.name: [round(float(c), 6) for c in sub["best_coverage"][k]]
                                   for k, t in enumerate(tasks)},
            "subpolicy_initiation_states": {t.name: len(t.initiation) for t in tasks},
            # the same sum with each sub-policy judged by the paper's single-start test
            "episodes_to_optimal_single_start": [p["single_start_total"] for p in per_trial],
            "coordinator_episodes_to_optimal": co["episodes_to_optimal"],
            "coordinator_episodes_to_solved": co["episodes_to_solved"],
            "coordinator_summary": summarize(co["episodes_to_optimal"]),
            "options": list(b["options"].names), "tasks": [t.name for t in tasks],
            **reference_metrics(b["reference"], co), "optimal_slack": cfg.train.optimal_slack,
            "best_team_test_return": co["best_return"].tolist(), "best_team_test_steps": co["best_length"].tolist(),
            # primitive actions of all agents in training: every sub-policy's episodes, then the coordinator's
            "env_steps": (sub_steps + np.asarray(co["env_steps"])).tolist(),
            "env_steps_by_stage": {"subpolicies": sub_steps.tolist(), "coordinator": np.asarray(co["env_steps"]).tolist()},
            "seconds": {"subpolicies": stage_seconds(sub_o), "coordinator": stage_seconds(co_o)},
            "config": cfg.to_dict(), "config_hash": cfg.hash(), "environment": environment_info(),
        }
        write_outputs(out, b, sub, co, best_sub, metrics, figures)
        for line in summary_lines(metrics, cfg.train.episodes, cfg.hierarchical.coordinator.episodes):
            print(f"[hierarchical] {line}", flush=True)
        return metrics


def write_outputs(out: Path, b: dict, sub: dict, co: dict, best_sub, metrics: dict, figures: bool = True) -> None:
    """curves.csv, params/, and with ``figures`` the figures and ``metrics["best_trial"]`` (its team episode)."""
    tasks, env = b["tasks"], b["env"]
    trials = co["train_return"].shape[0]
    with open(out / "curves.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["stage", "task", "trial", "kind", "episode", "return", "steps", "optimal", "start_optimal",
                    "coverage"])
        stages = [("subpolicy", t.name, {**{n: v[k] for n, v in sub.items() if n not in ("test_episode", "best_params")},
                                         "test_episode": sub["test_episode"]}) for k, t in enumerate(tasks)]
        for stage, name, r in stages + [("coordinator", "coordinator", co)]:
            for j in range(trials):
                for i, (ret, st) in enumerate(zip(r["train_return"][j], r["train_length"][j])):
                    if not np.isnan(ret):  # nan: not run (the trial stopped at optimal, train.stop_at_optimal)
                        w.writerow([stage, name, j, "train", i + 1, float(ret), int(st), "", "", ""])
                for e, ret, st, o, so, c in zip(r["test_episode"], r["test_return"][j], r["test_length"][j],
                                                r["test_optimal"][j], r["test_start_optimal"][j], r["test_coverage"][j]):
                    if np.isnan(ret):
                        continue
                    w.writerow([stage, name, j, "test", int(e), float(ret), int(st), int(o), int(so),
                                "" if np.isnan(c) else round(float(c), 6)])
    (out / "params").mkdir(exist_ok=True)
    for j in range(trials):
        blob = {"subpolicies": jax.tree.map(lambda x: np.asarray(x[j]), best_sub),
                "coordinator": jax.tree.map(lambda x: np.asarray(x[j]), co["best_params"])}
        (out / "params" / f"trial_{j}.msgpack").write_bytes(serialization.to_bytes(blob))
    if not figures:
        return
    # the optimum of a fixed-start task; random-start tasks have one per start (not drawn)
    opt = [int(b["task_params"].dist[k, t.test_starts[0, 3], t.test_starts[0, 0], t.test_starts[0, 1],
                                     t.test_starts[0, 2]])
           if len(t.test_starts) == 1 else -1 for k, t in enumerate(tasks)]
    names = [t.name for t in tasks]
    subpolicy_pages(sub, names, out, env.horizon, np.asarray(opt))
    for k, name in enumerate(names):  # and one figure per sub-policy, as the paper's Fig. 4 panels
        one = {**{n: v[k:k + 1] for n, v in sub.items()
                  if n in ("train_length", "test_length", "test_coverage", "best_length", "best_coverage")},
               "test_episode": sub["test_episode"]}
        subpolicy_figure(one, [name], out / f"fig4_{name.replace(':', '_').lower()}.png", env.horizon,
                         np.asarray(opt[k:k + 1]))
    training_figure(co, out / "coordinator.png", "coordinator (SMDP DQN over joint options)", horizon=env.horizon,
                    optimal_steps=b["optimal"], smooth_window=5, reward_range=reward_range(env),
                    reference=b["reference"]["reference"])
    # the best trial: optimal soonest, else the best team test
    order = sorted(range(trials), key=lambda j: (metrics["episodes_to_optimal"][j] is None,
                                                  metrics["episodes_to_optimal"][j] or 0,
                                                  -co["best_return"][j], co["best_length"][j]))
    j = order[0]
    tables = b["coordinator_params"](jax.tree.map(lambda x: x[j], best_sub), 1)  # its trial's alone
    states, rewards, decisions = team_episode(b["macro"], b["coord_learner"],
                                              jax.tree.map(lambda x: x[j], co["best_params"]), tables.subpolicy)
    from jaxusar.envs.render import ROLE_WORDS, save_episode_strip

    plan = "   ".join(f"{i + 1}) " + ", ".join(f"{ROLE_WORDS[env.roles[a]]} {a}: {o}" for a, o in enumerate(d[:-1]))
                       + ("" if d[-1] else " (invalid)") for i, d in enumerate(decisions))
    if len(plan) > TITLE_PLAN_CHARS:  # a long plan made a title of several lines wider than the frames
        plan = f"{len(decisions)} decisions, listed in metrics.json (best_trial)"
    save_episode_strip(env, states, out / "team_episode.png", rewards=rewards,
                       suptitle=f"best trial {j}: greedy coordinator + sub-policies, {len(rewards)} steps, "
                                f"return {rewards.sum():g}\nthe coordinator's joint options: {plan}")
    metrics["best_trial"] = {"trial": j, "steps": len(rewards), "return": float(rewards.sum()), "decisions": decisions}
