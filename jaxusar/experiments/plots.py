"""Figures in the style of the paper's Figs. 4-6: steps and rewards vs episodes, mean and band over trials."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


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
    mean = y.mean(0)
    (line,) = ax.plot(x, mean, label=label, color=color, lw=1.5)
    lo, hi = np.percentile(y, [25, 75], axis=0)
    ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.25, lw=0)
    ax.fill_between(x, y.min(0), y.max(0), color=line.get_color(), alpha=0.08, lw=0)
    return line


def training_figure(results: dict | list[tuple[str, dict]], path: str | Path, title: str,
                    horizon: int | None = None, optimal_steps: int | None = None, smooth_window: int = 20):
    """2x2 figure: train steps, train reward, test steps, test reward vs training episodes.

    ``results`` is one trainer result dict, or a list of (label, results) drawn on the same axes.
    """
    series = results if isinstance(results, list) else [(None, results)]
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for label, r in series:
        n = r["train_length"].shape[1]
        ep = np.arange(1, n + 1)
        band(axes[0, 0], ep, smooth(r["train_length"], smooth_window), label)
        band(axes[0, 1], ep, smooth(r["train_return"], smooth_window), label)
        band(axes[1, 0], r["test_episode"], r["test_length"], label)
        band(axes[1, 1], r["test_episode"], r["test_return"], label)
    for ax in axes[:, 0]:
        if horizon:
            ax.axhline(horizon, color="grey", ls=":", lw=1, label="horizon")
        if optimal_steps:
            ax.axhline(optimal_steps, color="green", ls="--", lw=1, label="optimal")
    axes[0, 0].set_title(f"train: steps per episode (moving avg {smooth_window})")
    axes[0, 1].set_title(f"train: team reward (moving avg {smooth_window})")
    axes[1, 0].set_title("greedy test: steps")
    axes[1, 1].set_title("greedy test: team reward")
    for ax in axes[1]:
        ax.set_xlabel("training episodes")
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8, loc="best")
    n_trials = series[0][1]["train_length"].shape[0]
    fig.suptitle(f"{title}  (line: mean of {n_trials} trials; band: 25-75th percentile; faint: min-max)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
