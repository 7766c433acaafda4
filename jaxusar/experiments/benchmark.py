"""``jaxusar benchmark``: every algorithm on every task of the suite, scored and aggregated as rliable does.

Each (task, algorithm) pair is the algorithm's own experiment (``jaxusar train``'s, same defaults and map
settings) with the task's observation and horizon, N trials. All trainers of all pairs run side by side in
one ``Runner`` (one per CPU core, the longest first, with checkpoints: an interrupted benchmark resumes
where it stopped), then each trial is scored:

* **score** of a greedy team episode: on a task with fixed victims, its return rate over the reference's,
  ``(R / R*) * min(1, T* / T)`` (R: return, T: steps, the horizon if it did not finish; R*, T*: the exact
  optimum's, or the lower bound's steps where the joint search is out of reach): 1 exactly at the optimum,
  ``T*/T`` for a team that saves everyone in T steps. With victims drawn at reset: ``R / R*`` with R* the
  clairvoyant optimum (or bound) of the same draw's mean, ``planning.clairvoyant_reference``: a bound no
  policy that must search can reach.
* a trial's **final score**: its kept (best-tested) params' greedy episodes on the task's test draws (the
  one fixed start, or ``task.test_draws`` draws from ``task.draw_seed``): mean R over mean R* there.
* **env steps**: primitive actions of all agents in training episodes (the paper's method: every
  sub-policy's and the coordinator's), ``core.Trainer``'s count; a trial's curve is its best test score so
  far against the env steps it had taken at that test.

Writes ``out`` (default results/benchmark)::

    results.json        tasks (ids, references), per pair: per-trial final scores, env steps, env steps to
                        90% of the reference, curves; aggregates with intervals; what could not run and why
    leaderboard.md      one row per algorithm: IQM, median, mean, optimality gap [95% CI], env steps to 90%
    tasks.md            per task: each algorithm's final scores (median, best, trials at >= 0.9)
    aggregates.png  profile.png  improvement.png  sample_efficiency.png
    runs/<task>/<algo>/ each pair's own results folder (metrics.json, curves.csv, params/, figures: none
                        with --quick, whose time goes to training)
    maps/               the generated tasks' layouts
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shlex
import shutil
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import numpy as np

from jaxusar import algos, config, envs, planning
from jaxusar.envs.layout import load_layout
from jaxusar.experiments import reproduce, stats, stdout, train
from jaxusar.experiments.runner import Runner, gather
from jaxusar.experiments.suite import Task, materialize, resolve
from jaxusar.experiments.plots import benchmark_figures, reward_range
from jaxusar.experiments.usage import Usage

ALGORITHMS = ("hierarchical", "doc", "iql", "vdn", "qmix", "scripted")
# Option-critic runs one K here: 2, the only one that learned in the paper (Table II, Fig. 5).
SETTINGS = {"doc": ["doc.options=[2]"]}
# --quick: reduced budgets and QUICK_TRIALS trials (unless --trials is given), the same pipeline, every task
# and algorithm (results/benchmark_quick/: its time on a 2-core AMD EPYC and Intel Xeon): compiling takes
# half, the paper's method's sub-policies most of the rest. Fewer trials rather than fewer than 20
# sub-policy episodes keep a learning signal in the paper's method's row (at 10 episodes it scores about
# 0, like the flat learners at 100); compiling does not shrink with either.
# Finished trials stay in the batch (train.drop_finished=false): at these budgets the chunks that a smaller
# batch would save take less than compiling its program (the paper's method on four_rooms, two_rooms_rubble
# and office, 2 trials alone on the 2-core AMD EPYC: 3-6 s less a map). The scripted team trains nothing.
QUICK = {"hierarchical": ["train.episodes=20", "hierarchical.coordinator.episodes=30", "train.drop_finished=false"],
         **{a: ["train.episodes=100", "train.drop_finished=false"] for a in ("doc", "iql", "vdn", "qmix")}}
# ... and where victims are drawn, 10 episodes per sub-policy: there the paper's method scores about 0 at
# either budget (minimap-v1: 0.004 at 20), and its 18 sub-policies' 10 episodes end within one chunk of
# 4,000 steps, not two (minimap-v1's sub-policy stage, alone on the 2-core AMD EPYC: 144 s at 20 episodes).
QUICK_DRAWN = {"hierarchical": ["train.episodes=10"]}
TRIALS, QUICK_TRIALS = 8, 2
TARGET = 0.9  # "env steps to 90% of the reference"
# A trainer's compiling and start, in ``reproduce.expected_cost``'s units, for the suite's time to go: about
# 9-14 s a trainer two at a time, and under --quick most of a flat learner's time (fit to the trainers'
# ends of three --quick runs on the 2-core AMD EPYC; without it the time to go said 26 s with 194 s left).
TRAINER_COST = 1.5e7
CURVE_POINTS = 40


# -- scores ---------------------------------------------------------------------------------------------
def episode_scores(returns, steps, ref_return, ref_steps=None) -> np.ndarray:
    """Scores of greedy episodes (module doc): ``(R / R*) * min(1, T* / T)``, or ``R / R*`` without ``ref_steps``."""
    score = np.asarray(returns, float) / float(ref_return)
    if ref_steps is None:
        return score
    return score * np.minimum(1.0, float(ref_steps) / np.maximum(np.asarray(steps, float), 1.0))


def final_scores(ret: np.ndarray, steps: np.ndarray, ref: dict) -> np.ndarray:
    """Per trial: the score of its greedy episodes ``ret``, ``steps`` [trials, draws] (module doc): mean R over
    R* where victims are drawn, else the one episode's ``episode_scores``."""
    if ref["steps"] is None:
        return ret.mean(1) / ref["return"]
    return episode_scores(ret[:, 0], steps[:, 0], ref["return"], ref["steps"])


def best_so_far(scores: np.ndarray) -> np.ndarray:
    """[trials, tests]: the best score up to each test (a test not run, nan, keeps the best before it; 0 first)."""
    return np.maximum.accumulate(np.nan_to_num(np.asarray(scores, float), nan=0.0), axis=-1)


def steps_to(curve_steps: np.ndarray, curve_scores: np.ndarray, target: float = TARGET) -> list:
    """Per trial: env steps at the first test whose score reached ``target`` (None: never)."""
    out = []
    for x, y in zip(curve_steps, curve_scores):
        hit = np.flatnonzero(np.asarray(y) >= target - 1e-9)
        out.append(int(x[hit[0]]) if hit.size else None)
    return out


def curve_on(grid: np.ndarray, curve_steps: np.ndarray, curve_scores: np.ndarray) -> np.ndarray:
    """[trials, len(grid)]: each trial's best score by ``grid`` env steps (0 before its first test)."""
    out = np.zeros((len(curve_steps), len(grid)))
    for k, (x, y) in enumerate(zip(curve_steps, curve_scores)):
        idx = np.searchsorted(np.asarray(x), grid, side="right") - 1
        out[k] = np.where(idx >= 0, np.asarray(y)[np.maximum(idx, 0)], 0.0)
    return out


# -- a task's references ---------------------------------------------------------------------------------
def reference(task: Task, env) -> dict:
    """What ``task`` is scored against: ``return`` (R*: mean over the test draws), ``steps`` (T*, fixed
    victims only, else None) and ``kind`` (optimum, lower bound, clairvoyant optimum or bound)."""
    if env.n_drawn:
        ref = planning.clairvoyant_reference(env, n_draws=task.test_draws, seed=task.draw_seed)
        return {"return": float(ref["return"]), "steps": None, "kind": ref["reference"], "draws": task.test_draws}
    ref = planning.team_reference(env)
    ret = ref.get("return", reward_range(env)[1] + env.step_penalty * ref["steps"])  # every victim triaged
    return {"return": float(ret), "steps": int(ref["steps"]), "kind": ref.get("return_reference", ref["reference"]),
            "draws": 1}


def test_keys(task: Task, env) -> jax.Array:
    n = task.test_draws if env.n_drawn else 1
    return jax.random.split(jax.random.PRNGKey(task.draw_seed), n)


# -- one (task, algorithm) pair ------------------------------------------------------------------------
@dataclasses.dataclass
class Pair:
    task: Task
    algo: str
    experiment: object
    prefix: str  # its stages' names in the shared Runner: "<task id>/<stage>"

    @property
    def chain(self) -> list:
        """The stages whose results score it: the experiment's only chain (option-critic runs one K here)."""
        return self.experiment.chains[0]


def configs(task: Task, map_: str, quick: bool, sets: list[str]) -> dict[str, config.ExperimentConfig]:
    """Each algorithm's config on ``task``: its defaults and the map's settings, the benchmark's own
    (SETTINGS), the task's observation and horizon, --quick budgets (and QUICK_DRAWN where victims are
    drawn), then ``sets`` (all or ``algo.``-prefixed)."""
    out, drawn = {}, quick and len(load_layout(map_).random_cells) > 0
    for a in ALGORITHMS:
        own = [f"env.map={json.dumps(map_)}", f"env.observation={task.observation}", f"env.horizon={task.horizon}",
               *SETTINGS.get(a, []), *(QUICK.get(a, []) if quick else []),
               *(QUICK_DRAWN.get(a, []) if drawn else [])]
        for s in sets:
            head = s.split(".", 1)[0]
            if head not in ALGORITHMS:
                own.append(s)
            elif head == a:
                own.append(s.split(".", 1)[1])
        try:
            out[a] = config.load(None, own, defaults=algos.defaults(a))
        except config.ConfigError as err:
            raise config.ConfigError(f"{task.id}, {a}: {err}") from None
    return out


def test_curve(stage, results: dict, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(env steps [trials, tests], returns, steps) of a trainer's greedy tests; ``offset`` [trials]: env
    steps taken before this stage (the sub-policies', for the coordinator)."""
    ran = ~np.isnan(np.asarray(results["train_return"], float))  # nan: an episode a stopped trial did not run
    lengths = np.where(ran, np.asarray(results["train_length"], float), 0.0)
    cum = np.concatenate([np.zeros((len(lengths), 1)), np.cumsum(lengths, 1)], 1) * stage.trainer.agents
    at = np.asarray(results["test_episode"], int)
    return offset[:, None] + cum[:, at], np.asarray(results["test_return"], float), \
        np.asarray(results["test_length"], float)


def score_pair(pair: Pair, outcomes: dict, ref: dict, keys: jax.Array) -> dict:
    """A pair's per-trial final scores, env steps, env steps to TARGET and best-so-far curve. A pair with
    nothing to train (the scripted team) plays its episodes as they are: its curve is its score from 0 env steps."""
    if not pair.experiment.chains:
        ep = pair.experiment.play(keys)
        ret, steps = np.asarray(ep["return"], float), np.asarray(ep["steps"], float)
        score = final_scores(ret, steps, ref)
        trials = len(score)
        return {"final_score": [round(float(v), 6) for v in score], "env_steps": [0] * trials,
                "env_steps_to_target": [0 if v >= TARGET - 1e-9 else None for v in score],
                "curve_env_steps": [[0]] * trials, "curve_score": [[round(float(v), 6)] for v in score],
                "final_return": ret.mean(1).round(4).tolist(), "final_steps": steps.mean(1).round(2).tolist()}
    chain = pair.chain
    last = chain[-1]
    results = {s.name: outcomes[f"{pair.prefix}/{s.name}"].results for s in chain}
    trials = len(last.keys)
    offset = np.zeros(trials)
    for s in chain[:-1]:  # the earlier stages' lanes, summed per trial
        offset += np.asarray(results[s.name]["env_steps"], float).reshape(trials, -1).sum(1)
    final = results[last.name]
    ep = train.kept_episodes(chain, lambda s: outcomes[f"{pair.prefix}/{s.name}"], keys)
    ret, steps = ep["return"], ep["steps"]
    score = final_scores(ret, steps, ref)
    x, test_ret, test_len = test_curve(last, final, offset)
    y = best_so_far(episode_scores(test_ret, test_len, ref["return"], ref["steps"]))
    env_steps = offset + np.asarray(final["env_steps"], float)
    return {"final_score": [round(float(v), 6) for v in score], "env_steps": [int(v) for v in env_steps],
            "env_steps_to_target": steps_to(x, y), "curve_env_steps": x.astype(np.int64).tolist(),
            "curve_score": np.round(y, 6).tolist(), "final_return": ret.mean(1).round(4).tolist(),
            "final_steps": steps.mean(1).round(2).tolist()}


def score_all(pairs: list[Pair], planned, outcomes: dict, out: Path, quick: bool, workers: int) -> dict:
    """Each pair's own results folder (its experiment's ``finish``) and scores, {(task id, algo): score_pair}.
    With ``quick`` (no figures: pyplot is not thread-safe) ``workers`` pairs at a time, as their greedy
    replays compile and run outside the GIL; each pair's printed lines come out together, in pair order,
    each led by its task's id (the experiments' own lines name only the algorithm)."""

    def one(pair: Pair) -> tuple[dict, str]:
        task, env, _, ref = next(p for p in planned if p[0] is pair.task)
        own = {name[len(pair.prefix) + 1:]: o for name, o in outcomes.items() if name.startswith(pair.prefix + "/")}
        folder = out / "runs" / task.id / pair.algo
        with stdout.captured() as text:
            metrics = pair.experiment.finish(folder, own, figures=not quick)
            (folder / "metrics.json").write_text(json.dumps(metrics, indent=2))
            score = score_pair(pair, outcomes, ref, test_keys(task, env))
        return score, text.getvalue()

    scored = {}
    with stdout.per_thread(), ThreadPoolExecutor(workers if quick else 1) as pool:
        for pair, (score, text) in zip(pairs, pool.map(one, pairs)):
            print("".join(f"[{pair.task.id}] {line}" for line in text.splitlines(keepends=True)), end="", flush=True)
            scored[pair.task.id, pair.algo] = score
    return scored


# -- the command ------------------------------------------------------------------------------------
def plan(tasks: list[Task], algorithms: list[str], explicit: bool, out: Path, quick: bool, sets: list[str]
         ) -> tuple[list[tuple[Task, object, dict, dict]], list[dict]]:
    """Per task: (task, env, the configs of the algorithms that can run it, reference), and the pairs that
    cannot run (``explicit``: when the user named both the tasks and the algorithms, such a pair is an
    error instead). Configs are all checked before any map is planned."""
    cfgs = {task.id: configs(task, materialize(task, out / "maps"), quick, sets) for task in tasks}
    planned, skipped = [], []
    for task in tasks:
        mine = cfgs[task.id]
        env = envs.make(mine[ALGORITHMS[0]].env.map, **mine[ALGORITHMS[0]].env.overrides())
        why = {a: train.unsupported(a, mine[a]) for a in algorithms}
        for a, reason in why.items():
            if reason and explicit:
                raise config.ConfigError(f"{a} cannot run {task.id}: {reason}")
            if reason:
                skipped.append({"task": task.id, "algorithm": a, "why": reason})
        planned.append((task, env, {a: mine[a] for a in algorithms if not why[a]}, reference(task, env)))
    return planned, skipped


def trial_count(trials: int | None, quick: bool) -> int:
    """``--trials`` as given, else TRIALS (QUICK_TRIALS with ``--quick``)."""
    return (QUICK_TRIALS if quick else TRIALS) if trials is None else trials


def check_algorithms(names: list[str] | None) -> list[str]:
    if not names:
        return list(ALGORITHMS)
    bad = [a for a in names if a not in ALGORITHMS]
    if bad:
        raise config.ConfigError(f"unknown algorithm(s) {', '.join(map(repr, bad))}; the benchmark runs "
                                 f"{', '.join(ALGORITHMS)}")
    if len(set(names)) != len(names):
        raise config.ConfigError(f"--algorithms names an algorithm twice: {' '.join(names)}")
    return [a for a in ALGORITHMS if a in names]


def suite_progress(chains: list, quiet: bool):
    """Each trainer's progress lines, and after each trainer ends one line on the whole suite: trainers done,
    their share of the expected work (``reproduce.expected_cost`` and ``TRAINER_COST`` each, a rough bound)
    and the time to go at that pace. Called from the Runner's threads."""
    if quiet:
        return None
    cost = {s.name: reproduce.expected_cost(s) + TRAINER_COST for c in chains for s in c}
    total, done, start, lock = sum(cost.values()), set(), time.perf_counter(), threading.Lock()

    def progress(name: str, p: dict) -> None:
        train.print_progress(name, p)
        finished = p["finished"] if "resumed_from" in p else p["episodes_min"] >= p["episodes_total"]
        with lock:
            if not finished or name in done:
                return
            done.add(name)
            share = sum(cost[n] for n in done) / total
            elapsed = time.perf_counter() - start
            to_go = f"about {elapsed * (1 - share) / share:.0f} s to go" if share < 1 else "all trained"
            print(f"[benchmark] {len(done)}/{len(cost)} trainers done ({share:.0%} of the expected work), "
                  f"{elapsed:.0f} s elapsed, {to_go}", flush=True)

    return progress


def fingerprint(planned, trials: int) -> str:
    text = json.dumps({"trials": trials, **{f"{t.id}/{a}": c.hash() for t, _, cfgs, _ in planned
                                            for a, c in cfgs.items()}}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def run(tasks: list[str] | None = None, algorithms: list[str] | None = None, trials: int | None = None,
        out: str | Path | None = None, quick: bool = False, sets: list[str] | None = None, force: bool = False,
        quiet: bool = False, checkpoint_every: float = 60.0, workers: int | None = None, devices=None,
        command: str | None = None) -> dict:
    """The suite (module doc); returns results.json's dict. Bad input fails before anything compiles.
    ``trials``: default TRIALS, or QUICK_TRIALS with ``quick``."""
    start, usage, sets = time.perf_counter(), Usage(), list(sets or [])
    trials = trial_count(trials, quick)
    chosen, names = resolve(tasks), check_algorithms(algorithms)
    out = Path(out or Path("results") / "benchmark")
    with train.removed_if_refused(out):
        out = train.prepare_out(out, force, marker="results.json")
        seed = config.load(None, [s for s in sets if s.split(".", 1)[0] not in ALGORITHMS]).seed
        keys = train.trial_keys(seed, trials, devices)  # a --trials that cannot split fails first
        planned, skipped = plan(chosen, names, bool(tasks) and bool(algorithms), out, quick, sets)
        if {c.seed for _, _, cfgs, _ in planned for c in cfgs.values()} != {seed}:
            raise config.ConfigError("every algorithm must use the same seed (the trials are the same seeds)")
        runner = Runner(out / "checkpoints", fingerprint(planned, trials), checkpoint_every, devices)
        try:
            pairs = []
            for task, _, cfgs, _ in planned:
                for a, cfg in cfgs.items():
                    folder = out / "runs" / task.id / a
                    folder.mkdir(parents=True, exist_ok=True)
                    pairs.append(Pair(task, a, train.experiment(cfg, keys), f"{task.id}/{a}"))
            chains = [[dataclasses.replace(s, name=f"{p.prefix}/{s.name}") for s in c]
                      for p in pairs for c in p.experiment.chains]
            chains.sort(key=lambda c: -sum(reproduce.expected_cost(s) for s in c))  # longest first
            runner.progress = suite_progress(chains, quiet)
            n_workers = train.worker_count(len(chains), workers)
            if not quiet:
                print(f"[benchmark] {len(planned)} tasks x {len(names)} algorithms ({len(pairs)} runs, "
                      f"{len(skipped)} cannot run), {trials} trials each; {len(chains)} trainers, {n_workers} at a "
                      f"time; writing {out}", flush=True)
            outcomes = runner.run(chains, workers=n_workers)
            outcomes = gather(outcomes, {s.name: s for c in chains for s in c})
            if jax.process_index() != 0:
                return {}
            scored = score_all(pairs, planned, outcomes, out, quick, n_workers)
        except KeyboardInterrupt:
            raise runner.interrupted() from None
    results = summarize(planned, names, scored, skipped, trials, quick)
    results["command"] = command or shlex.join(["jaxusar", "benchmark", "--trials", str(trials), "--out", str(out)]
                                               + (["--quick"] if quick else []))
    results["wall_seconds"] = round(time.perf_counter() - start, 2)
    results["usage"] = usage.report()
    results["environment"] = train.environment_info()
    write(out, results)
    shutil.rmtree(out / "checkpoints", ignore_errors=True)
    if not quiet:
        print("\n" + (out / "leaderboard.md").read_text(), flush=True)
    print(f"[benchmark] {results['wall_seconds']:.1f}s in all; wrote {out}", flush=True)
    return results


def summarize(planned, names, scored, skipped, trials, quick) -> dict:
    """results.json: tasks and references, per pair its scores and curves, per algorithm the aggregates."""
    tasks = {t.id: {"describe": t.describe(), "observation": t.observation, "horizon": t.horizon,
                    "reference": ref, "config_hashes": {a: c.hash() for a, c in cfgs.items()}}
             for t, _, cfgs, ref in planned}
    per_algo = {}
    for a in names:
        ids = [t for t in tasks if (t, a) in scored]
        if not ids:
            continue
        final = np.array([scored[t, a]["final_score"] for t in ids]).T  # [runs, tasks]
        agg = stats.aggregates(final)
        hits = [s for t in ids for s in scored[t, a]["env_steps_to_target"]]
        reached = [s for s in hits if s is not None]
        per_algo[a] = {"tasks": ids, "aggregates": {k: list(v) for k, v in agg.items()},
                       "runs_reaching_target": f"{len(reached)}/{len(hits)}",
                       "median_env_steps_to_target": int(np.median(reached)) if reached else None,
                       "env_steps_median": int(np.median([s for t in ids for s in scored[t, a]["env_steps"]]))}
    return {"trials": trials, "quick": quick, "target": TARGET, "tasks": tasks, "algorithms": per_algo,
            "runs": {f"{t}/{a}": v for (t, a), v in scored.items()}, "cannot_run": skipped}


def _ci(e) -> str:
    return f"{e[0]:.3f} [{e[1]:.3f}, {e[2]:.3f}]"


def leaderboard(results: dict) -> str:
    rows = ["| algorithm | tasks | IQM | median | mean | optimality gap | runs at >= 90% | env steps to 90% (median) |",
            "|---|---:|---:|---:|---:|---:|---:|---:|"]
    order = sorted(results["algorithms"], key=lambda a: -results["algorithms"][a]["aggregates"]["iqm"][0])
    for a in order:
        r = results["algorithms"][a]
        g = r["aggregates"]
        steps = "never" if r["median_env_steps_to_target"] is None else f"{r['median_env_steps_to_target']:,}"
        rows.append(f"| {a} | {len(r['tasks'])} | {_ci(g['iqm'])} | {_ci(g['median'])} | {_ci(g['mean'])} | "
                    f"{_ci(g['optimality_gap'])} | {r['runs_reaching_target']} | {steps} |")
    lines = [f"# Leaderboard{' (--quick budgets)' if results['quick'] else ''}", "",
             f"{results['trials']} trials per task; final normalized scores (1 = the task's reference), aggregated "
             "over runs x tasks with stratified bootstrap 95% intervals (rliable); env steps = primitive actions "
             "of all agents in training. Written by `" + results["command"] + "`.", "", *rows]
    if results["cannot_run"]:
        lines += ["", "Not run (an algorithm on a task it cannot run): " + "; ".join(
            f"{c['algorithm']} on {c['task']} ({c['why']})" for c in results["cannot_run"])]
    return "\n".join(lines) + "\n"


def task_tables(results: dict) -> str:
    lines = ["# Per task", ""]
    for tid, t in results["tasks"].items():
        ref = t["reference"]
        steps = "" if ref["steps"] is None else f", {ref['steps']} steps"
        lines += [f"## {tid}", "", f"{t['describe']}. Reference: {ref['kind']}, return {ref['return']:g}{steps}"
                  f" ({ref['draws']} test draw{'s' if ref['draws'] > 1 else ''}).", "",
                  "| algorithm | median score | best | trials at >= 90% | median env steps |",
                  "|---|---:|---:|---:|---:|"]
        for key, r in results["runs"].items():
            if key.rsplit("/", 1)[0] != tid:
                continue
            s = np.asarray(r["final_score"])
            at = sum(v is not None for v in r["env_steps_to_target"])
            lines.append(f"| {key.rsplit('/', 1)[1]} | {np.median(s):.3f} | {s.max():.3f} | {at}/{len(s)} | "
                         f"{int(np.median(r['env_steps'])):,} |")
        lines.append("")
    return "\n".join(lines)


def write(out: Path, results: dict) -> None:
    (out / "results.json").write_text(json.dumps(results, indent=2))
    (out / "leaderboard.md").write_text(leaderboard(results))
    (out / "tasks.md").write_text(task_tables(results))
    benchmark_figures(results, out)
