"""Figures in the style of the paper's Figs. 4-6: steps and rewards vs episodes, mean and band over trials."""

from __future__ import annotations

import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def kept(curve: np.ndarray, best: np.ndarray) -> np.ndarray:
    """A test curve [trials, tests] whose tests a stopped trial did not run (nan: ``stop_at_optimal``) show
    its kept params' test (``best`` [trials]: the first optimal one), which it ends with. The last test it
    ran may be later and worse: a trial stops at the end of the chunk of its first optimal test."""
    curve = np.asarray(curve, float)
    return np.where(np.isnan(curve), np.asarray(best, float)[..., None], curve)


def smooth(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average along the last axis (window shrinks at the start)."""
    if window <= 1:
        return x
    c = np.cumsum(np.asarray(x, float), axis=-1)
    out = c.copy()
    out[..., window:] = c[..., window:] - c[..., :-window]
    n = np.minimum(np.arange(1, x.shape[-1] + 1), window)
    return out / n


def band(ax, x, y, label=None, color=None, spread: bool = True):
    """Mean over trials (axis 0) with a band from the 25th to the 75th percentile and, with ``spread``,
    min-max faint (left out where several series share the axes: their faint bands blur together)."""
    y = np.asarray(y, float)
    with warnings.catch_warnings():  # nan: episodes a stopped trial did not run (train.stop_at_optimal)
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(y, 0)
        (line,) = ax.plot(x, mean, label=label, color=color, lw=1.5)
        lo, hi = np.nanpercentile(y, [25, 75], axis=0)
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.25, lw=0)
        if spread:
            ax.fill_between(x, np.nanmin(y, 0), np.nanmax(y, 0), color=line.get_color(), alpha=0.08, lw=0)
    return line


def band_key(fig, n_trials: int, color: str = "tab:blue", extra: dict | None = None, spread: bool = True,
             ncol: int | None = None) -> None:
    """A legend under the figure saying what ``band``'s line and shades are (and ``extra`` label: artist),
    in rows of ``ncol`` entries (default: one row)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    entries = {f"mean of {n_trials} trials": Line2D([], [], color=color, lw=1.5),
               "25th-75th percentile of trials": Patch(color=color, alpha=0.35, lw=0)}
    if spread:
        entries["lowest to highest trial"] = Patch(color=color, alpha=0.1, lw=0)
    entries.update(extra or {})
    fig.legend(list(entries.values()), list(entries), loc="lower center", ncol=ncol or len(entries), frameon=False,
               fontsize=9)


def reward_range(env) -> tuple[float, float]:
    """(the team return of an episode that triages nothing, of one that triages every victim at once)."""
    critical = int(np.sum(env.victim_kind == 1))  # envs.CRITICAL: critical_reward each
    best = (env.n_victims - critical) * env.triage_reward + critical * env.critical_reward
    return env.horizon * env.step_penalty, best


def training_figure(results: dict | list[tuple[str, dict]], path: str | Path, title: str,
                    horizon: int | None = None, optimal_steps: int | None = None, smooth_window: int = 20,
                    reward_range: tuple[float, float] | None = None, reference: str = "optimum"):
    """2x2 figure: train steps, train reward, test steps, test reward vs training episodes.

    ``results`` is one trainer result dict, or a list of (label, results) drawn on the same axes (each
    with its mean and interquartile band, keyed under the figure). ``reward_range``: (the return of an
    episode that triages nothing, the best possible return); the reward axes span it and stop a little
    below it (returns lower still, the coordinator's invalid-option penalties, are cut off, and the axis
    says so), and a figure whose greedy tests never beat the first says so. ``reference``: what
    ``optimal_steps`` is, "optimum" or "lower bound" (``planning.team_reference``).
    """
    from matplotlib.lines import Line2D

    series = results if isinstance(results, list) else [(None, results)]
    spread = len(series) == 1
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.4), sharex=True)
    top, bottom = [-np.inf, -np.inf], [np.inf, np.inf]  # the highest and lowest reward drawn, per row
    for label, r in series:
        n = r["train_length"].shape[1]
        ep = np.arange(1, n + 1)
        rewards = smooth(r["train_return"], smooth_window), kept(r["test_return"], r["best_return"])
        band(axes[0, 0], ep, smooth(r["train_length"], smooth_window), label, spread=spread)
        band(axes[0, 1], ep, rewards[0], label, spread=spread)
        band(axes[1, 0], r["test_episode"], kept(r["test_length"], r["best_length"]), label, spread=spread)
        band(axes[1, 1], r["test_episode"], rewards[1], label, spread=spread)
        for row, y in enumerate(rewards):
            if np.isfinite(y).any():
                top[row], bottom[row] = max(top[row], float(np.nanmax(y))), min(bottom[row], float(np.nanmin(y)))
    for ax in axes[:, 0]:
        if horizon:
            ax.axhline(horizon, color="grey", ls=":", lw=1)
            ax.set_ylim(0, horizon * 1.05)
        if optimal_steps:
            ax.axhline(optimal_steps, color="green", ls="--", lw=1)
        ax.set_ylabel("steps per episode")
    for row, ax in enumerate(axes[:, 1]):
        ax.set_ylabel("team reward per episode")
        if reward_range is not None:
            lo, hi = reward_range
            pad = 0.05 * (hi - lo)
            ax.set_ylim(lo - pad, max(top[row], hi) + pad)
            if bottom[row] < lo - pad:
                ax.text(0.01, 0.01, f"cut off below {lo - pad:g} (invalid-option penalties)", transform=ax.transAxes,
                        fontsize=8, color="grey", va="bottom")
    if reward_range is not None and max(float(np.nanmax(r["test_return"])) for _, r in series) <= reward_range[0]:
        axes[1, 1].text(0.5, 0.5, "no greedy test triaged a victim\nwithin this budget", transform=axes[1, 1].transAxes,
                        ha="center", va="center", fontsize=11, color="tab:red")
    axes[0, 0].set_title(f"train: steps per episode (moving avg {smooth_window})")
    axes[0, 1].set_title(f"train: team reward (moving avg {smooth_window})")
    axes[1, 0].set_title("greedy test: steps")
    axes[1, 1].set_title("greedy test: team reward")
    for ax in axes[1]:
        ax.set_xlabel("training episodes")
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
    n_trials = series[0][1]["train_length"].shape[0]
    extra = {}
    if series[0][0] is not None:  # the series' colours, in the key under the axes (not over the curves)
        extra = {label: Line2D([], [], color=line.get_color(), lw=1.5)
                 for (label, _), line in zip(series, axes[0, 0].get_lines())}
    extra["horizon (episode cap)"] = Line2D([], [], color="grey", ls=":", lw=1)
    if optimal_steps:
        name = "optimal" if reference == "optimum" else "lower bound"
        extra[f"{name} ({optimal_steps} steps)"] = Line2D([], [], color="green", ls="--", lw=1)
    ncol = 4 if len(extra) > 2 else None
    band_key(fig, n_trials, color="grey" if len(series) > 1 else "tab:blue", extra=extra, spread=spread, ncol=ncol)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.08 if ncol else 0.04, 1, 1))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# -- the benchmark's figures (rliable style) -----------------------------------------------------------
ALGO_COLORS = {"hierarchical": "tab:green", "doc": "tab:purple", "iql": "tab:blue", "vdn": "tab:orange",
               "qmix": "tab:red", "scripted": "tab:gray"}


def _algo_color(name: str, i: int) -> str:
    return ALGO_COLORS.get(name, f"C{i}")


def _save(fig, path: Path) -> Path:
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def benchmark_figures(results: dict, out: Path) -> list[Path]:
    """aggregates.png (IQM, median, mean, optimality gap with 95% intervals), profile.png (performance
    profiles), improvement.png (probability of improvement, every pair), sample_efficiency.png (IQM score
    vs env steps) from ``jaxusar benchmark``'s results.json dict. Each algorithm keeps one colour throughout."""
    from jaxusar.experiments import stats

    algos_ = results["algorithms"]
    names = sorted(algos_, key=lambda a: algos_[a]["aggregates"]["iqm"][0])  # best on top
    colors = {a: _algo_color(a, i) for i, a in enumerate(algos_)}
    finals = {a: np.array([results["runs"][f"{t}/{a}"]["final_score"] for t in algos_[a]["tasks"]]).T for a in names}
    paths = []

    fig, axes = plt.subplots(1, 4, figsize=(12, 1.2 + 0.45 * len(names)), sharey=True, layout="constrained")
    for ax, metric in zip(axes, stats.AGGREGATES):
        for y, a in enumerate(names):
            point, low, high = algos_[a]["aggregates"][metric]
            ax.barh(y, high - low, left=low, height=0.6, color=colors[a], alpha=0.75)
            ax.plot([point, point], [y - 0.3, y + 0.3], color="black", lw=1.5)
        ax.set_title(metric.replace("_", " ").replace("iqm", "IQM"))
        ax.set_xlabel("normalized score")
        # the whole score range, with room at both ends: a point at 0 or at the reference is not on the frame
        top = max(1.0, *(algos_[a]["aggregates"][metric][2] for a in names))
        ax.set_xlim(-0.03 * top, 1.03 * top)
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_yticks(range(len(names)), [f"{a} ({len(algos_[a]['tasks'])} tasks)" for a in names])
    fig.suptitle("aggregate final scores, 95% stratified bootstrap intervals (bar) and point estimate (line)")
    paths.append(_save(fig, out / "aggregates.png"))

    taus = np.linspace(0, 1.05, 64)
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for a in reversed(names):
        p = stats.performance_profile(finals[a], taus)
        ax.plot(taus, p.point, color=colors[a], label=a, lw=1.8)
        ax.fill_between(taus, p.low, p.high, color=colors[a], alpha=0.2, lw=0)
    ax.set_xlabel("normalized score tau")
    ax.set_ylabel("fraction of runs with score > tau")
    ax.set_title("performance profiles (95% bands)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=9, frameon=False)
    paths.append(_save(fig, out / "profile.png"))

    common = [t for t in results["tasks"] if all(t in algos_[a]["tasks"] for a in names)]
    if len(names) > 1 and common:
        arrays = {a: np.array([results["runs"][f"{t}/{a}"]["final_score"] for t in common]).T
                  for a in reversed(names)}
        pairs = stats.probabilities_of_improvement(arrays)
        fig, ax = plt.subplots(figsize=(7, 0.6 + 0.38 * len(pairs)))
        for y, ((x_name, y_name), e) in enumerate(pairs.items()):
            ax.barh(y, e.high - e.low, left=e.low, height=0.6, color=colors[x_name], alpha=0.75)
            ax.plot([e.point, e.point], [y - 0.3, y + 0.3], color="black", lw=1.5)
        ax.set_yticks(range(len(pairs)), [f"P({x} > {y})" for x, y in pairs])
        ax.axvline(0.5, color="grey", ls=":", lw=1)
        ax.set_xlim(-0.03, 1.03)  # a certain improvement (1) is not drawn on the frame
        ax.set_xlabel("probability of improvement")
        ax.set_title(f"on the {len(common)} tasks every algorithm ran (95% intervals)")
        ax.grid(axis="x", alpha=0.3)
        paths.append(_save(fig, out / "improvement.png"))

    steps = [s for r in results["runs"].values() for trial in r["curve_env_steps"] for s in trial]
    grid = np.geomspace(max(1.0, min(s for s in steps if s > 0)), max(steps), 40)
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    from jaxusar.experiments.benchmark import curve_on

    for a in reversed(names):
        curves = np.stack([curve_on(grid, results["runs"][f"{t}/{a}"]["curve_env_steps"],
                                    results["runs"][f"{t}/{a}"]["curve_score"]) for t in algos_[a]["tasks"]], 1)
        e = stats.iqm_curve(curves)
        ax.plot(grid, e.point, color=colors[a], label=a, lw=1.8)
        ax.fill_between(grid, e.low, e.high, color=colors[a], alpha=0.2, lw=0)
    ax.set_xscale("log")
    ax.set_xlabel("env steps (primitive actions of all agents, training)")
    ax.set_ylabel("IQM of best greedy test score so far")
    ax.set_ylim(0, 1.05)
    ax.set_title("sample efficiency (95% bands)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=9, frameon=False)
    paths.append(_save(fig, out / "sample_efficiency.png"))
    return paths
