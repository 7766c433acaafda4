"""Run one algorithm's N trials and write its results folder (side effects live here, not in core).

An algorithm's experiment is an object with ``chains`` (lists of ``runner.Stage``: the trainers to run),
``finish(out, outcomes, figures=True) -> metrics`` (writes everything but metrics.json, the figures only with
``figures``: ``benchmark --quick`` writes none per run; prints the result lines) and
``FIGURES`` (the figures it writes, for ``jaxusar train --help``). A flat learner
(IQL, or a fork's ``jaxusar/algos/<name>.py`` with ``ALGORITHM`` and ``make_learner``) gets
``FlatExperiment``; the hierarchical method and option-critic name theirs (``EXPERIMENT``:
``jaxusar/experiments/hierarchical.py``, ``doc.py``).
``run`` drives one experiment (``jaxusar train``); ``jaxusar.experiments.reproduce`` drives several.

Output folder of a flat learner (default ``runs/<algo>-<map>``, ``default_out``)::

    metrics.json        algorithm, trials, episodes_to_optimal (list over trials, null = never),
                        summary statistics, env_steps (per trial: primitive actions of all agents in
                        training episodes), wall_seconds (compile included), resolved config, versions
    curves.csv          trial, kind (train|test), episode, return, steps, optimal
    params/trial_K.msgpack   best test params of trial K (flax.serialization)
    curves.png          train and test steps and rewards vs episodes, band over trials (paper Fig. 6 style)
    checkpoints/        while running: the trainers' states (removed when the run has finished)
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import importlib
import json
import os
import platform
import shutil
import time
from pathlib import Path

import flax
import jax
import numpy as np
import optax
from flax import serialization

from jaxusar import algos, envs, planning
from jaxusar.config import ConfigError, ExperimentConfig
from jaxusar.core import Trainer
from jaxusar.core.trainer import trial_devices
from jaxusar.experiments.runner import Outcome, Runner, Stage, gather
from jaxusar.experiments.plots import reward_range, training_figure
from jaxusar.experiments.stats import in_words, summarize
from jaxusar.experiments.usage import Usage


def environment_info() -> dict:
    return {"jax": jax.__version__, "flax": flax.__version__, "optax": optax.__version__,
            "numpy": np.__version__, "python": platform.python_version(), "machine": platform.machine(),
            "processor": cpu_name(), "cpu_count": os.cpu_count(), "devices": [str(d) for d in jax.devices()]}


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def print_progress(name: str, p: dict) -> None:
    """One progress line of trainer ``name`` (``p``: what Trainer.train reports after a chunk, or the
    Runner's notice that the stage resumed from a checkpoint)."""
    if "resumed_from" in p:
        done = "finished before, not run again" if p["finished"] else f"continuing after chunk {p['chunk']}"
        print(f"[{name}] resumed from {p['resumed_from']}: {done} ({p['run_seconds']:.0f} s of training "
              "done before)", flush=True)
        return
    to_go = "time to go not known yet" if p["eta"] is None else f"about {p['eta']:.0f} s to go"
    print(f"[{name}] chunk {p['chunk']}: episodes done {p['episodes_min']}/{p['episodes_total']} in the slowest "
          f"trial (mean {p['episodes_mean']:.0f}); {p['elapsed']:.0f} s elapsed, {to_go}", flush=True)


def build(cfg: ExperimentConfig):
    """env, reference (``planning.team_reference``), learner, trainer for a flat (non-hierarchical) algorithm."""
    env = envs.make(cfg.env.map, **cfg.env.overrides())
    reference = planning.team_reference(env)
    learner = algos.algorithm(cfg.algo).make_learner(env, cfg.dqn)
    trainer = Trainer(env, learner, cfg.train, learning_starts=cfg.dqn.learning_starts,
                      train_every=cfg.dqn.train_every, gradient_steps=cfg.dqn.gradient_steps,
                      optimal_steps=reference["steps"])
    return env, reference, learner, trainer


def trial_keys(seed: int, trials: int, devices=None) -> jax.Array:
    """One PRNG key per trial; with several processes (jax.distributed), this process's contiguous share.

    Checks up front that the trials split evenly over the processes and over each process's
    ``devices`` (default: its local devices), so a bad count fails before anything compiles."""
    if trials < 1:
        raise ConfigError(f"--trials must be >= 1, got {trials}")
    n, i = jax.process_count(), jax.process_index()
    if trials % n:
        raise ConfigError(f"--trials {trials} cannot be split evenly over {n} processes")
    per = trials // n
    local = len(trial_devices(devices))
    if per % local:
        raise ConfigError(f"--trials {trials} cannot be split evenly over {n * local} devices "
                          f"({n} process(es) x {local}); use a multiple of {n * local}")
    return all_trial_keys(seed, trials)[i * per:(i + 1) * per]


def all_trial_keys(seed: int, trials: int) -> jax.Array:
    """Every process's trial keys together (``trial_keys`` gives each process its share)."""
    return jax.random.split(jax.random.PRNGKey(seed), trials)


def write_curves_csv(path: Path, results: dict) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["trial", "kind", "episode", "return", "steps", "optimal"])
        for k in range(results["train_return"].shape[0]):
            for i, (r, s) in enumerate(zip(results["train_return"][k], results["train_length"][k])):
                if not np.isnan(r):  # nan: not run (train.stop_at_optimal)
                    w.writerow([k, "train", i + 1, float(r), int(s), ""])
            for e, r, s, o in zip(results["test_episode"], results["test_return"][k], results["test_length"][k],
                                  results["test_optimal"][k]):
                if not np.isnan(r):
                    w.writerow([k, "test", int(e), float(r), int(s), int(o)])


def save_params(folder: Path, best_params) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    n = jax.tree.leaves(best_params)[0].shape[0]
    for k in range(n):
        trial = jax.tree.map(lambda x: np.asarray(x[k]), best_params)
        (folder / f"trial_{k}.msgpack").write_bytes(serialization.to_bytes(trial))


def default_out(cfg: ExperimentConfig) -> Path:
    """``runs/<algo>-<map>`` (a layout path's file name without .txt), so runs on two maps do not collide."""
    return Path("runs") / f"{cfg.algo}-{Path(cfg.env.map).stem}"


def run_fingerprint(cfg: ExperimentConfig, trials: int) -> str:
    """What a checkpoint must have been written by to resume: the config and the number of trials."""
    return hashlib.sha256(json.dumps({"trials": trials, "config": cfg.hash()}).encode()).hexdigest()[:12]


def prepare_out(out: str | Path, force: bool, marker: str = "metrics.json") -> Path:
    """Create ``out``; refuse if a finished run (its ``marker`` file) is there, unless ``force``, which
    also drops the checkpoints of an unfinished one (else a re-run resumes from them)."""
    out = Path(out)
    if (out / marker).exists() and not force:
        raise FileExistsError(f"{out / marker} exists: a finished run is never overwritten; write this one "
                              "elsewhere with --out DIR, or pass --force to replace it")
    try:
        if force:
            shutil.rmtree(out / "checkpoints", ignore_errors=True)
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise FileExistsError(f"cannot create the output folder {str(out)!r}: {err.strerror or err}") from None
    return out


@contextlib.contextmanager
def removed_if_refused(out: str | Path):
    """Run a command that writes into ``out``: if it ends with an error (bad input found late, Ctrl-C
    before the first checkpoint), the folders it created there and left empty are removed again."""
    out = Path(out).absolute()
    new = [p for p in (out, *out.parents) if not p.exists()]
    root = new[-1] if new else out
    before = set() if new else {Path(d) for d, _, _ in os.walk(out)}
    try:
        yield
    except BaseException:
        if root.is_dir():
            for folder, _, _ in os.walk(root, topdown=False):  # deepest first: a parent empties after its children
                if Path(folder) not in before:
                    with contextlib.suppress(OSError):  # not empty: something was written there
                        os.rmdir(folder)
        raise


def stage_seconds(outcome: Outcome) -> dict:
    return {"compile": round(outcome.compile_seconds, 2), "run": round(outcome.run_seconds, 2),
            "chunks": outcome.chunks, "resumed_from_chunk": outcome.resumed_from_chunk}


def reference_metrics(reference: dict, results: dict) -> dict:
    """The team's reference (exact optimum or lower bound) and each trial's optimality gap: its shortest
    solving test's steps / the lower bound (None where no test triaged every victim)."""
    solved = [e is not None for e in results["episodes_to_solved"]]
    return {"optimal_team_steps": reference["steps"], "reference": reference["reference"],
            "team_lower_bound": reference["lower_bound"],
            "optimality_gap": [round(int(s) / reference["lower_bound"], 4) if ok else None
                               for s, ok in zip(results["best_length"], solved)]}


def unsupported(algo: str, cfg: ExperimentConfig) -> str | None:
    """Why ``algo`` cannot run as ``cfg`` says (one line, before anything compiles), or None: for the
    paper's method ``hierarchical.setup``'s refusals (an option kind the map cannot offer, a flat
    coordinator past its joint options)."""
    if algo == "hierarchical":
        from jaxusar.experiments import hierarchical

        try:
            hierarchical.setup(cfg)
        except ConfigError as err:
            return str(err)
    return None


def kept_episodes(chain: list, outcome, keys: jax.Array) -> dict:
    """``greedy_episodes`` of a chain's kept (best-tested) params, its last stage's. ``outcome(stage)``: a
    stage's ``Outcome``; a stage whose env params come from the one before (the coordinator's) gets them."""
    last = chain[-1]
    env_params = last.env_params
    if callable(env_params):
        env_params = env_params(outcome(chain[-2]))
    return greedy_episodes(last.trainer, outcome(last).results["best_params"], keys, env_params)


def greedy_episodes(trainer, params, keys: jax.Array, env_params=None) -> dict:
    """Greedy team episodes of per-trial ``params`` (and ``env_params``, if any), one per trial and reset
    key: arrays [trials, keys] of ``return``, ``steps``, ``saved`` and ``critical_saved`` (victims
    triaged, critical ones among them; the keys ``scripted.judge`` scores)."""
    from jaxusar.envs.usar import CRITICAL

    per_key = jax.vmap(trainer.greedy_rollout, in_axes=(None, 0, None))
    per_trial = jax.vmap(per_key, in_axes=(0, None, None if env_params is None else 0))
    ret, steps, _, _, final = jax.jit(per_trial)(params, keys, env_params)
    world = getattr(trainer.env, "env", trainer.env)  # the coordinator's macro env wraps the team env
    triaged = np.asarray(getattr(final, "env", final).triaged)  # the macro env's state holds the team env's
    critical = np.asarray(world.victim_kind) == CRITICAL
    return {"return": np.asarray(ret, float), "steps": np.asarray(steps, float), "saved": triaged.sum(-1),
            "critical_saved": (triaged & critical).sum(-1)}


def flat_metrics(cfg: ExperimentConfig, results: dict, reference: dict, outcome: Outcome, **extra) -> dict:
    """metrics.json of one Trainer's results (``extra`` keys go after ``algorithm``)."""
    eto = results["episodes_to_optimal"]
    return {
        "algorithm": cfg.algo, **extra, "trials": len(eto), "episodes_to_optimal": eto, **summarize(eto),
        "episodes_to_solved": results["episodes_to_solved"],
        **reference_metrics(reference, results), "optimal_slack": cfg.train.optimal_slack,
        "best_test_return": results["best_return"].tolist(), "best_test_steps": results["best_length"].tolist(),
        "env_steps": results["env_steps"].tolist(), "seconds": stage_seconds(outcome),
        "config": cfg.to_dict(), "config_hash": cfg.hash(), "environment": environment_info(),
    }


def write_trial_files(out: Path, results: dict) -> None:
    """curves.csv and params/ of one Trainer's results."""
    write_curves_csv(out / "curves.csv", results)
    save_params(out / "params", results["best_params"])


class FlatExperiment:
    """One Trainer over the trials: IQL, or any learner in jaxusar/algos without an EXPERIMENT of its own."""

    FIGURES = ("curves.png",)

    def __init__(self, cfg: ExperimentConfig, keys: jax.Array):
        self.cfg = cfg
        self.env, self.reference, _, trainer = build(cfg)
        self.chains = [[Stage(cfg.algo, trainer, keys)]]

    def finish(self, out: Path, outcomes: dict[str, Outcome], figures: bool = True) -> dict:
        cfg, o = self.cfg, outcomes[self.cfg.algo]
        results = o.results
        metrics = flat_metrics(cfg, results, self.reference, o)
        write_trial_files(out, results)
        if figures:
            training_figure(results, out / "curves.png", f"{cfg.algo} on {cfg.env.map}", horizon=self.env.horizon,
                            optimal_steps=self.reference["steps"], reward_range=reward_range(self.env),
                            reference=self.reference["reference"])
        print(f"[{cfg.algo}] {in_words(results['episodes_to_optimal'], cfg.train.episodes)}", flush=True)
        return metrics


def experiment_class(algo: str):
    """The experiment class of ``algo``: its ``EXPERIMENT`` module's, else FlatExperiment."""
    name = getattr(algos.algorithm(algo), "EXPERIMENT", None)
    return FlatExperiment if name is None else importlib.import_module(name).Experiment


def experiment(cfg: ExperimentConfig, keys: jax.Array, **extra):
    """The experiment object of ``cfg.algo``: its ``EXPERIMENT`` module's, else a FlatExperiment."""
    cls = experiment_class(cfg.algo)
    if cls is FlatExperiment and extra:
        raise ConfigError(f"{sorted(extra)} do not apply to {cfg.algo}")
    return cls(cfg, keys, **extra)


def stage_progress(quiet: bool):
    return None if quiet else print_progress


def run(cfg: ExperimentConfig, trials: int, out: str | Path | None = None, force: bool = False,
        quiet: bool = False, checkpoint_every: float = 60.0, devices=None, command: str | None = None,
        **extra) -> dict:
    """Train ``trials`` seeds of ``cfg.algo`` (one vmapped call per trainer) and write the results folder
    ``out`` (default ``default_out(cfg)``).

    Resumes from ``out/checkpoints`` if an earlier run of the same config was interrupted. Returns metrics;
    ``command`` (the command line that ran it) is recorded in them. ``quiet``: no progress lines (the
    result lines are printed all the same). Ctrl-C raises ``runner.Interrupted``.
    """
    start, usage = time.perf_counter(), Usage()
    keys = trial_keys(cfg.seed, trials, devices)
    out = default_out(cfg) if out is None else Path(out)
    with removed_if_refused(out):
        out = prepare_out(out, force)
        runner = Runner(out / "checkpoints", run_fingerprint(cfg, trials), checkpoint_every, devices,
                        stage_progress(quiet))
        try:
            exp = experiment(cfg, keys, **extra)
            outcomes = runner.run(exp.chains, workers=worker_count(len(exp.chains)))
            outcomes = gather(outcomes, {s.name: s for chain in exp.chains for s in chain})
            if jax.process_index() != 0:
                return {}
            metrics = exp.finish(out, outcomes)
        except KeyboardInterrupt:
            raise runner.interrupted() from None
    metrics["wall_seconds"] = round(time.perf_counter() - start, 2)
    metrics["command"] = command
    metrics["usage"] = usage.report()
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    shutil.rmtree(out / "checkpoints", ignore_errors=True)
    print(f"[{cfg.algo}] {metrics['wall_seconds']:.1f}s; wrote {out}", flush=True)
    return metrics


def worker_count(chains: int, workers: int | None = None) -> int:
    """Chains trained side by side: by default one per CPU core (a vmapped call keeps about one busy)."""
    return max(1, min(chains, workers or os.cpu_count() or 1))
