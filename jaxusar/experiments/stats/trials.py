"""Statistics over trials of episodes-to-optimal, where a trial may never get there.

The paper reports its best trial of 8, because a mean can mislead. We report that, and also the
median, the interquartile mean (IQM: the mean of the middle half, ``scipy.stats.trim_mean(x, 0.25)``,
Agarwal et al. 2021) with a 95% percentile-bootstrap interval over trials, and the fraction of trials
that ever reach optimal.

A trial that never reached optimal within the budget counts as +inf (censored: it would have needed
more episodes than were run). So a statistic is finite only if the never-trials fall outside what it
averages: the IQM is finite when at most a quarter of the trials never got there, a bootstrap bound
when enough resamples have that property. An infinite value is reported as None, read "more than the
budget". Bootstrap percentiles are order statistics (no interpolation), so they are exact with inf.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.stats import trim_mean


def _as_array(episodes_to_optimal) -> np.ndarray:
    return np.asarray([np.inf if e is None else e for e in episodes_to_optimal], float)


def _finite_or_none(x: float):
    return float(x) if math.isfinite(x) else None


def iqm(episodes_to_optimal) -> float | None:
    x = _as_array(episodes_to_optimal)
    return _finite_or_none(trim_mean(x, 0.25)) if len(x) else None


def bootstrap_ci(episodes_to_optimal, level: float = 0.95, resamples: int = 10_000, seed: int = 0):
    """Percentile-bootstrap interval of the IQM over trials: [low, high], None = above the budget."""
    x = _as_array(episodes_to_optimal)
    if len(x) == 0:
        return [None, None]
    rng = np.random.default_rng(seed)
    stats = trim_mean(x[rng.integers(0, len(x), (resamples, len(x)))], 0.25, axis=1)
    lo, hi = np.quantile(stats, [(1 - level) / 2, (1 + level) / 2], method="inverted_cdf")
    return [_finite_or_none(lo), _finite_or_none(hi)]


def summarize(episodes_to_optimal: list) -> dict:
    """best, median, IQM and its 95% bootstrap interval, fraction of trials that reached optimal."""
    x = np.sort(_as_array(episodes_to_optimal))
    n = len(x)
    reached = x[np.isfinite(x)]
    return {"best": int(reached[0]) if len(reached) else None,
            "median": _finite_or_none(np.median(x)) if n else None,
            "iqm": iqm(episodes_to_optimal), "iqm_ci95": bootstrap_ci(episodes_to_optimal),
            "fraction_optimal": len(reached) / n if n else 0.0}


def in_words(episodes_to_optimal: list, budget: int) -> str:
    """The trials' episodes to optimal as a sentence for the console (never = not within ``budget``)."""
    n, reached = len(episodes_to_optimal), sorted(e for e in episodes_to_optimal if e is not None)
    if not reached:
        return f"optimal in 0 of {n} trials (never within {budget:,} episodes)"
    text = f"optimal in {len(reached)} of {n} trials, after {', '.join(f'{e:,}' for e in reached)} episodes"
    if len(reached) < n:
        text += f"; never within {budget:,} in the other {n - len(reached)}"
    median = summarize(episodes_to_optimal)["median"]
    return text + f"; median {f'{median:,.0f}' if median is not None else f'> {budget:,}'}"
