"""``jaxusar reproduce``: the paper's Table II and Figs. 4-6 in one command.

Runs the hierarchical method, option-critic (K = 2, 4, 8) and IQL, each with N trials in one vmapped
call per trainer, all trainers side by side (one per CPU core), with resumable checkpoints, plays the
scripted team (no learning, the bar every learned team must clear; a row of the table where victims are
fixed), and writes::

    results.json          per algorithm (and per K): episodes_to_optimal per trial (null = never), best,
                          median, IQM with its 95% bootstrap interval, fraction of trials optimal, episodes
                          to the first test solved at any length, each trial's best test steps, its env
                          steps (primitive actions of all agents in training), compile and
                          run seconds per trainer; seconds_by_algorithm (setup, compile, run, write); the
                          planner's optimum; this invocation's wall seconds; versions, config hashes, the
                          machine, workers, devices and processes
    table2.md             the paper's Table II beside ours, and the paper's method stage by stage; on a map
                          whose victims are drawn at reset, each team's normalized score over the scripted
                          team's fixed judging draws instead (``drawn_table``)
    fig4_subpolicies.png  sub-policy train/test steps vs episodes (paper Fig. 4; 8 sub-policies a page, then
                          fig4_subpolicies_2.png, ...)
    fig5_doc.png          option-critic, the K on one figure (paper Fig. 5)
    fig6_iql.png          IQL (paper Fig. 6)
    team_episode.png      the best hierarchical trial's greedy team episode, frame by frame
    hierarchical/ doc/ iql/   each algorithm's own results folder (metrics.json, curves.csv, params/, ...)
    checkpoints/          while running (removed at the end): every trainer's state, for resuming

Each algorithm's settings are its defaults (= ``configs/<algo>.yaml``) and the map's; ``--quick`` lowers the
budgets (QUICK below) for a first look in minutes (docs/performance.md: its time). ``sets`` override
settings of every algorithm (``env.horizon=200``) or of one (``iql.train.episodes=100``).
"""

from __future__ import annotations

import hashlib
import json
import shlex
import shutil
import time
from pathlib import Path

import jax
import numpy as np

from jaxusar import algos, config, envs
from jaxusar.core.trainer import trial_devices
from jaxusar.experiments import scripted as sc
from jaxusar.experiments import train
from jaxusar.experiments.runner import Runner, gather
from jaxusar.experiments.stats import summarize
from jaxusar.experiments.usage import Usage

ALGORITHMS = ("hierarchical", "doc", "iql", "scripted")

# Table II of the paper: episodes to reach the optimal policy, best of 8 trials. Only its 2-option
# option-critic learned; 4 and 8 options stayed at the step cap for all 5000 episodes (Fig. 5).
PAPER_TABLE2 = {"hierarchical": "1030", "doc_K2": "1,500", "doc_K4": "never (> 5,000)", "doc_K8": "never (> 5,000)",
                "iql": "> 5,000"}
LABELS = {"hierarchical": "Hierarchical (sub-policies + coordinator)", "doc": "Distributed option-critic",
          "iql": "Independent Q-learning", "scripted": "Scripted team (no learning; the bar to clear)"}

# --quick: the same pipeline on budgets that finish in minutes on a 2-core CPU (docs/performance.md: its time).
QUICK = {
    "hierarchical": ["train.episodes=150", "hierarchical.coordinator.episodes=30"],
    "doc": ["train.episodes=200"],
    "iql": ["train.episodes=200"],
    "scripted": [],
}

FIGURES = {"fig4_subpolicies.png": "hierarchical/fig4_subpolicies.png", "fig5_doc.png": "doc/fig5_doc.png",
           "fig6_iql.png": "iql/curves.png", "team_episode.png": "hierarchical/team_episode.png"}


def configs(quick: bool = False, sets: list[str] | None = None, map: str | None = None
            ) -> dict[str, config.ExperimentConfig]:
    """Each algorithm's config: its defaults, the --quick budgets, the map, then ``sets`` (all, or
    ``algo.``-prefixed)."""
    own: dict[str, list[str]] = {a: (list(QUICK[a]) if quick else []) + ([f"env.map={json.dumps(map)}"] if map else [])
                                 for a in ALGORITHMS}
    for s in sets or []:
        head = s.split(".", 1)[0]
        for a in ALGORITHMS if head not in ALGORITHMS else (head,):
            own[a].append(s if head not in ALGORITHMS else s.split(".", 1)[1])
    out = {}
    for a in ALGORITHMS:
        try:
            out[a] = config.load(None, own[a], defaults=algos.defaults(a))
        except config.ConfigError as err:
            raise config.ConfigError(f"{a}: {err}") from None
    return out


def fingerprint(cfgs: dict, trials: int) -> str:
    text = json.dumps({"trials": trials, **{a: c.hash() for a, c in cfgs.items()}}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def default_out(map: str | None) -> Path:
    """results/<map name> (a layout path's file name without .txt)."""
    return Path("results") / (Path(map).stem if map else config.EnvConfig.map)


def run(trials: int = 8, out: str | Path | None = None, quick: bool = False, sets: list[str] | None = None,
        force: bool = False, quiet: bool = False, checkpoint_every: float = 60.0, workers: int | None = None,
        devices=None, command: str | None = None, map: str | None = None) -> dict:
    """Everything above, on ``map`` (a shipped map's name or a layout path; default two_rooms), into
    ``out`` (default ``default_out(map)``); returns the results.json dict (in every process; only process 0
    writes). ``command``: the command line that ran it, for results.json (default: one that gives the same run)."""
    start, usage = time.perf_counter(), Usage()
    cfgs = configs(quick, sets, map)  # bad settings fail here, before anything compiles
    if len({c.env.map for c in cfgs.values()}) != 1:
        raise config.ConfigError("every algorithm must run on the same map (set env.map for all, or use --map)")
    out = default_out(cfgs["iql"].env.map) if out is None else out
    keys = train.trial_keys(cfgs["iql"].seed, trials, devices)
    if len({c.seed for c in cfgs.values()}) != 1:
        raise config.ConfigError("every algorithm must use the same seed (the trials are the same seeds)")
    env = envs.make(cfgs["iql"].env.map, **cfgs["iql"].env.overrides())
    with train.removed_if_refused(out):
        out = train.prepare_out(out, force, marker="results.json")
        folders = {a: out / a for a in ALGORITHMS}
        for f in folders.values():
            f.mkdir(exist_ok=True)
        runner = Runner(out / "checkpoints", fingerprint(cfgs, trials), checkpoint_every, devices,
                        train.stage_progress(quiet))
        try:
            setup = {}
            experiments = {}
            for a in ALGORITHMS:  # build (and plan) every algorithm before training any
                t = time.perf_counter()
                experiments[a] = train.experiment(cfgs[a], keys)
                setup[a] = time.perf_counter() - t
            chains = [c for a in ALGORITHMS for c in experiments[a].chains]
            chains.sort(key=lambda c: -sum(expected_cost(s) for s in c))  # longest first
            n_workers = train.worker_count(len(chains), workers)
            if not quiet:
                print(f"[reproduce] {trials} trials; {len(chains)} trainers, {n_workers} at a time; "
                      f"{len(trial_devices(devices))} device(s) per trainer; writing {out}", flush=True)
            outcomes = runner.run(chains, workers=n_workers)
            outcomes = gather(outcomes, {s.name: s for c in chains for s in c})
            train_seconds = time.perf_counter() - start
            if jax.process_index() != 0:
                return {}

            per_algorithm, seconds, judged = {}, {}, {}
            for a in ALGORITHMS:
                t = time.perf_counter()
                metrics = experiments[a].finish(folders[a], outcomes)
                if env.n_drawn:  # judged on the scripted team's draws: one set for every algorithm and trial
                    for chain in experiments[a].chains:
                        episodes = train.kept_episodes(chain, lambda s: outcomes[s.name], sc.judging_keys(env))
                        judged[row_key(a, chain)] = sc.judge(env, episodes)
                (folders[a] / "metrics.json").write_text(json.dumps(metrics, indent=2))
                per_algorithm[a] = metrics
                stages = [outcomes[s.name] for chain in experiments[a].chains for s in chain]
                seconds[a] = {"setup": round(setup[a], 2), "compile": round(sum(o.compile_seconds for o in stages), 2),
                              "run": round(sum(o.run_seconds for o in stages), 2),
                              "write": round(time.perf_counter() - t, 2)}
        except KeyboardInterrupt:
            raise runner.interrupted() from None
    for name, source in FIGURES.items():
        shutil.copyfile(out / source, out / name)
    for page in sorted((out / "hierarchical").glob("fig4_subpolicies_*.png")):  # past 8 sub-policies
        shutil.copyfile(page, out / page.name)

    results = summary(per_algorithm, cfgs, trials, quick, judged)
    results["command"] = command or shlex.join(
        ["jaxusar", "reproduce", "--trials", str(trials), "--out", str(out)] + (["--quick"] if quick else [])
        + (["--map", map] if map else [])
        + [a for s in sets or [] for a in ("--set", s)])
    results["seconds_by_algorithm"] = seconds
    results["wall_seconds"] = round(time.perf_counter() - start, 2)
    results["usage"] = usage.report()
    results["wall_seconds_training"] = round(train_seconds, 2)
    results["workers"] = n_workers
    results["devices_per_trainer"] = len(trial_devices(devices))
    results["processes"] = jax.process_count()
    results["resumed"] = any(o.resumed_from_chunk is not None for o in outcomes.values())
    (out / "table2.md").write_text(table2(results))
    (out / "results.json").write_text(json.dumps(results, indent=2))
    shutil.rmtree(out / "checkpoints", ignore_errors=True)
    print("\n" + (out / "table2.md").read_text(), flush=True)
    print(f"[reproduce] {results['wall_seconds']:.1f}s in all; wrote {out}", flush=True)
    return results


def expected_cost(stage) -> float:
    """A rough size of a stage's work, to start the longest first: lanes x env steps (episodes x horizon,
    a bound) x the work per env step (acting on one observation, and the replay ratio's share of a
    batch through forward and backward, about three passes per sample)."""
    t = stage.trainer
    per_step = 1 + 3 * t.learner.cfg.batch_size * t.gradient_steps / t.train_every
    return len(stage.keys) * t.cfg.episodes * t.test_horizon * per_step


STATS = ("episodes_to_optimal", "best", "median", "iqm", "iqm_ci95", "fraction_optimal")


def _row(metrics: dict, budget: int, seconds: dict, solved: list, best_steps: list) -> dict:
    """One Table II row; ``solved``: per trial, training episodes to the first greedy test that triaged
    every victim at any length (None = never); ``best_steps``: per trial, steps of its best test;
    ``optimality_gap``: per trial, its shortest solving test / the lower bound (None = never solved)."""
    return {**{k: metrics[k] for k in STATS}, "budget_episodes": budget, "episodes_to_solved": solved,
            "best_test_steps": [int(x) for x in best_steps], "optimality_gap": metrics["optimality_gap"],
            "env_steps": metrics["env_steps"], "seconds": seconds}


def row_key(algo: str, chain: list) -> str:
    """A chain's row in results.json: the algorithm, or ``doc_K<k>`` for option-critic's chain of K options."""
    return f"doc_{chain[-1].name.split('/')[-1]}" if algo == "doc" else algo


def summary(per_algorithm: dict, cfgs: dict, trials: int, quick: bool, judged: dict | None = None) -> dict:
    """results.json: one row per algorithm (per K for option-critic), statistics over trials. ``judged``:
    on a map whose victims are drawn, each row's ``scripted.judge`` scores (normalized score, draws with
    every victim saved, critical victims saved)."""
    rows = {}
    if "hierarchical" in per_algorithm:
        h, ch = per_algorithm["hierarchical"], cfgs["hierarchical"]
        stages = h["seconds"].values()
        totals = {k: round(sum(st[k] for st in stages), 2) for k in ("compile", "run")}
        n_sub, n_coord = ch.train.episodes, ch.hierarchical.coordinator.episodes
        rows["hierarchical"] = _row(h, n_sub * len(h["tasks"]) + n_coord, {**totals, "stages": h["seconds"]},
                                    h["coordinator_episodes_to_solved"], h["best_team_test_steps"])
        rows["hierarchical"].update(
            coordinator_episodes_to_optimal=h["coordinator_episodes_to_optimal"],
            subpolicy_episodes_to_optimal=h["subpolicy_episodes_to_optimal"],
            subpolicy_episodes_to_start_optimal=h["subpolicy_episodes_to_start_optimal"],
            episodes_to_optimal_single_start=h["episodes_to_optimal_single_start"],
            subpolicy_coverage=h["subpolicy_coverage"], subpolicy_initiation_states=h["subpolicy_initiation_states"],
            budget_episodes_per_subpolicy=n_sub, budget_episodes_coordinator=n_coord)
    d, i, sc_ = (per_algorithm[a] for a in ("doc", "iql", "scripted"))
    for k, m in d["per_options"].items():
        rows[f"doc_K{k}"] = _row(m, cfgs["doc"].train.episodes, m["seconds"], m["episodes_to_solved"],
                                 m["best_test_steps"])
    rows["iql"] = _row(i, cfgs["iql"].train.episodes, i["seconds"], i["episodes_to_solved"], i["best_test_steps"])
    if "optimal" in sc_:  # fixed victims: optimal or not from the start, with no episode spent
        optimal = [0 if ok else None for ok in sc_["optimal"]]
        solved = [None if gap is None else 0 for gap in sc_["optimality_gap"]]
        rows["scripted"] = _row({**summarize(optimal), "episodes_to_optimal": optimal,
                                 "optimality_gap": sc_["optimality_gap"], "env_steps": sc_["env_steps"]},
                                0, {}, solved, sc_["team_steps"])
    else:  # drawn victims: judged as the learned rows are, nothing else to show
        rows["scripted"] = {"budget_episodes": 0, "env_steps": sc_["env_steps"]}
        judged = {**(judged or {}), "scripted": {k: v for k, v in sc_.items() if k in JUDGED}}
    for key, j in (judged or {}).items():
        rows[key]["judged"] = {k: v for k, v in j.items() if k in JUDGED}
    return {
        "trials": trials, "quick": quick, "map": cfgs["iql"].env.map, "optimal_team_steps": i["optimal_team_steps"],
        "reference": i["reference"], "team_lower_bound": i["team_lower_bound"], "algorithms": rows,
        "paper_table2_best_of_8": PAPER_TABLE2,
        "config_hashes": {a: c.hash() for a, c in cfgs.items()},
        "environment": train.environment_info(),
    }


# what a row keeps of ``scripted.judge`` on a map whose victims are drawn
JUDGED = ("normalized_score", "normalized", "fraction_all_saved", "critical_saved", "critical_victims",
          "mean_return", "reference", "reference_return")


def _episodes(x) -> str:
    return "never" if x is None else f"{x:,.0f}"


def _label(key: str) -> str:
    algo, _, k = key.partition("_K")
    return LABELS[algo] + (f", {k} options" if k else "")


def drawn_table(results: dict) -> str:
    """The table of a map whose victims are drawn at reset: each algorithm's normalized score over the
    fixed judging draws (``scripted.judge``), with its spread over trials, draws with every victim saved and
    critical victims saved."""
    rows = {k: r for k, r in results["algorithms"].items() if "judged" in r}
    first = next(iter(rows.values()))["judged"]
    lines = [
        f"# {results['map']}: normalized scores over {sc.DRAWS} fixed draws",
        "",
        f"Victims are drawn at every reset, so every team is judged on the same {sc.DRAWS} draws (reset keys "
        f"from seed {sc.DRAW_SEED}, apart from every training seed): a trial's **normalized score** is its kept "
        "greedy team's mean return over the draws divided by the clairvoyant "
        f"{first['reference'].replace('clairvoyant ', '')}'s ({first['reference_return']:.0f}: the best return "
        "knowing where the victims are, `planning.clairvoyant_reference`), which no team that must search can "
        f"reach. {results['trials']} trials each; IQM = interquartile mean over trials with a 95% percentile-"
        f"bootstrap interval. Regenerate with `{results['command']}`.",
        "",
        "| Method | Normalized score: median | IQM [95% CI] | Best trial | Worst trial | Draws with every victim "
        f"saved | Critical saved (of {first['critical_victims']}) | Budget (episodes) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key, r in rows.items():
        j = r["judged"]
        n, (lo, hi) = j["normalized"], j["normalized"]["iqm_ci95"]
        budget = f"{r['budget_episodes']:,}" if r["budget_episodes"] else "none"
        lines.append(f"| {_label(key)} | {n['median']:.3f} | {n['iqm']:.3f} [{lo:.3f}, {hi:.3f}] | {n['best']:.3f} | "
                     f"{min(j['normalized_score']):.3f} | {np.mean(j['fraction_all_saved']):.1%} | "
                     f"{np.mean(j['critical_saved']):.2f} | {budget} |")
    lines += ["", "Draws with every victim saved and critical saved: means over the trials (per trial in "
              "results.json, `judged`).", "",
              "Per-trial numbers, seconds and versions: results.json."]
    return "\n".join(lines) + "\n"


def table2(results: dict) -> str:
    """The paper's Table II (best of 8) beside our best trial and the statistics over all trials; on a map
    whose victims are drawn, ``drawn_table``."""
    rows = results["algorithms"]
    if any("judged" in r for r in rows.values()):
        return drawn_table(results)
    steps, bound = results["optimal_team_steps"], results.get("team_lower_bound")
    exact = results.get("reference", "optimum") == "optimum"
    paper_map = results["map"] == config.EnvConfig.map  # the paper's Table II is for its map only
    lines = [
        f"# Table II: episodes to the optimal policy ({results['map']}, "
        + (f"optimum {steps} team steps)" if exact else f"lower bound {steps} team steps)"),
        "",
        ("Paper: best of 8 trials (its map only). " if paper_map else "")
        + f"Ours: {results['trials']} trials each; a trial that never reached optimal within "
        "its budget counts as never (> budget); IQM = interquartile mean over trials with a 95% percentile-bootstrap "
        "interval. Regenerate with `" + results["command"] + "`."
        + ("" if exact else f" The exact optimum of this map is out of the joint search's reach; teams are measured "
           f"against the lower bound ({steps} steps: the best assignment of victims to medics with exact "
           "single-medic tours, collisions ignored), so 'optimal' means a test of exactly that many steps, which "
           "the bound proves optimal, and the gap column shows how far the others are."),
        "",
        "| Method | Paper (best of 8) | Ours: best trial | Trials optimal | Median | IQM [95% CI] | Budget | "
        "Trials solved (any length) | Shortest test | Gap to lower bound: median (best) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, r in rows.items():
        label = _label(key)
        paper = PAPER_TABLE2.get(key, "-") if paper_map else "-"
        if r["budget_episodes"]:
            cells = _stats_cells(r["episodes_to_optimal"], r["budget_episodes"]) + f" | {r['budget_episodes']:,}"
        else:  # no learning: optimal from the start or never
            cells = f"- | {_count(r['episodes_to_optimal'])} | - | - | none"
        lines.append(f"| {label} | {paper} | {cells} | {_count(r.get('episodes_to_solved'))} | "
                     f"{_shortest(r.get('best_test_steps'))} | {_gap(r.get('optimality_gap'))} |")
    h = rows.get("hierarchical")
    if h and "episodes_to_optimal_single_start" in h:
        lines.append(f"| {LABELS['hierarchical']}, each sub-policy judged by the paper's single-start test | "
                     f"{PAPER_TABLE2['hierarchical'] if paper_map else '-'} | "
                     + _stats_cells(h["episodes_to_optimal_single_start"], h["budget_episodes"]) +
                     f" | {h['budget_episodes']:,} | - | - | - |")
    lines += ["", "Solved: a greedy test triaged every victim, at any length; shortest test: the fewest steps of "
              f"any trial's best greedy test; gap: a trial's shortest solving test / the lower bound ({bound} steps), "
              "median over the solved trials (1.00 = provably optimal). Hierarchical: a trial's count is the sum "
              "of its sub-policies' "
              "episodes to optimal (from every initiation state, below) plus the coordinator's (the paper's "
              "accounting); the budget is the sum of the sub-policy and coordinator budgets."]
    if h and "subpolicy_episodes_to_optimal" in h:
        lines += ["", "## The paper's method, stage by stage", ""] + stage_table(h, steps, exact)
    lines += ["", "Per-trial numbers, seconds and versions: results.json."]
    return "\n".join(lines) + "\n"


def stage_table(h: dict, optimal_team_steps: int, exact: bool = True) -> list[str]:
    """The hierarchical row of results.json, stage by stage: each sub-policy by both criteria (its whole
    initiation set, and the paper's single-start test), the kept params' coverage, the coordinator."""
    sub, n_sub = h["subpolicy_episodes_to_optimal"], h["budget_episodes_per_subpolicy"]
    start, cov = h["subpolicy_episodes_to_start_optimal"], h["subpolicy_coverage"]
    states = h["subpolicy_initiation_states"]
    n_tasks = len(sub["per_task"])
    lines = [
        "A sub-policy is optimal when its greedy policy reaches the sub-goal on a shortest path from every state "
        "of its option's initiation set (every open cell and facing where the coordinator may start or re-issue "
        "it; exact, from the planner's distance tables); the paper's single-start test (the greedy episode from "
        "the medic's start, or from a random room cell for triage) is its own column. The coordinator is "
        f"optimal when its greedy team episode (over the trial's kept sub-policies) takes the {optimal_team_steps}-"
        f"step {'optimum' if exact else 'lower bound'}. Kept params: the test with the most initiation states "
        "optimal.", "",
        "| Stage | Best trial | Trials optimal | Median | IQM [95% CI] | Budget | Single start: trials optimal, "
        "median | Kept params: states optimal, worst trial / mean |",
        "|---|---|---|---|---|---|---|---|"]
    rows = [(f"all {n_tasks} sub-policies (sum)", sub["sum"], n_sub * n_tasks, None)]
    rows += [(name, eto, n_sub, name) for name, eto in sub["per_task"].items()]
    rows += [("coordinator, over its trial's sub-policies", h["coordinator_episodes_to_optimal"],
              h["budget_episodes_coordinator"], None)]
    for name, eto, budget, task in rows:
        extra = " - | - |"
        if task is not None:
            c = np.asarray(cov[task])
            s = summarize(start[task])
            median = "> {:,}".format(budget) if s["median"] is None else f"{s['median']:,.0f}"
            extra = (f" {_count(start[task])}, {median} | {c.min():.1%} / {c.mean():.1%} of {states[task]} |")
        lines.append(f"| {name} | " + _stats_cells(eto, budget) + f" | {budget:,} |" + extra)
    return lines


def _gap(gaps) -> str:
    solved = [g for g in gaps or [] if g is not None]
    return "-" if not solved else f"{float(np.median(solved)):.2f} ({min(solved):.2f})"


def _count(episodes) -> str:
    return "-" if episodes is None else f"{sum(e is not None for e in episodes)}/{len(episodes)}"


def _shortest(steps) -> str:
    return "-" if not steps else str(min(steps))


def _stats_cells(episodes_to_optimal: list, budget: int) -> str:
    """best | reached/n | median | IQM [CI], a never (None) shown as '> budget'."""
    s = summarize(episodes_to_optimal)
    above = f"> {budget:,}"
    show = lambda x: above if x is None else f"{x:,.0f}"  # noqa: E731
    lo, hi = s["iqm_ci95"]
    n = len(episodes_to_optimal)
    return (f"{_episodes(s['best'])} | {round(s['fraction_optimal'] * n)}/{n} | {show(s['median'])} | "
            f"{show(s['iqm'])} [{show(lo)}, {show(hi)}]")

