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


def band(ax, x, y, label=None, color=None):
    """Mean over trials (axis 0) with a band from the 25th to the 75th percentile and min-max faint."""
    y = np.asarray(y, float)
    with warnings.catch_warnings():  # nan: episodes a stopped trial did not run (train.stop_at_optimal)
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(y, 0)
        (line,) = ax.plot(x, mean, label=label, color=color, lw=1.5)
        lo, hi = np.nanpercentile(y, [25, 75], axis=0)
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.25, lw=0)
        ax.fill_between(x, np.nanmin(y, 0), np.nanmax(y, 0), color=line.get_color(), alpha=0.08, lw=0)
    return line


def band_key(fig, n_trials: int, color: str = "tab:blue", extra: dict | None = None) -> None:
    """A legend under the figure saying what ``band``'s line and two shades are (and ``extra`` label: artist)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    entries = {f"mean of {n_trials} trials": Line2D([], [], color=color, lw=1.5),
               "25th-75th percentile of trials": Patch(color=color, alpha=0.35, lw=0),
               "lowest to highest trial": Patch(color=color, alpha=0.1, lw=0), **(extra or {})}
    fig.legend(list(entries.values()), list(entries), loc="lower center", ncol=len(entries), frameon=False,
               fontsize=9)


def reward_range(env) -> tuple[float, float]:
    """(the team return of an episode that triages nothing, of one that triages every victim at once)."""
    return env.horizon * env.step_penalty, env.n_victims * env.triage_reward


def training_figure(results: dict | list[tuple[str, dict]], path: str | Path, title: str,
                    horizon: int | None = None, optimal_steps: int | None = None, smooth_window: int = 20,
                    reward_range: tuple[float, float] | None = None):
    """2x2 figure: train steps, train reward, test steps, test reward vs training episodes.

    ``results`` is one trainer result dict, or a list of (label, results) drawn on the same axes.
    ``reward_range``: (the return of an episode that triages nothing, the best possible return); the
    reward axes span at least it, and a figure whose greedy tests never beat the first says so.
    """
    from matplotlib.lines import Line2D

    series = results if isinstance(results, list) else [(None, results)]
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.4), sharex=True)
    for label, r in series:
        n = r["train_length"].shape[1]
        ep = np.arange(1, n + 1)
        band(axes[0, 0], ep, smooth(r["train_length"], smooth_window), label)
        band(axes[0, 1], ep, smooth(r["train_return"], smooth_window), label)
        band(axes[1, 0], r["test_episode"], kept(r["test_length"], r["best_length"]), label)
        band(axes[1, 1], r["test_episode"], kept(r["test_return"], r["best_return"]), label)
    for ax in axes[:, 0]:
        if horizon:
            ax.axhline(horizon, color="grey", ls=":", lw=1)
            ax.set_ylim(0, horizon * 1.05)
        if optimal_steps:
            ax.axhline(optimal_steps, color="green", ls="--", lw=1)
        ax.set_ylabel("steps per episode")
    for ax in axes[:, 1]:
        ax.set_ylabel("team reward per episode")
        if reward_range is not None:
            lo, hi = reward_range
            y0, y1 = ax.get_ylim()
            pad = 0.05 * (hi - lo)
            ax.set_ylim(min(y0, lo - pad), max(y1, hi + pad))
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
    if series[0][0] is not None:
        axes[0, 0].legend(fontsize=8, loc="upper right")
    n_trials = series[0][1]["train_length"].shape[0]
    extra = {"horizon (episode cap)": Line2D([], [], color="grey", ls=":", lw=1)}
    if optimal_steps:
        extra[f"optimal ({optimal_steps} steps)"] = Line2D([], [], color="green", ls="--", lw=1)
    band_key(fig, n_trials, color="grey" if len(series) > 1 else "tab:blue", extra=extra)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
