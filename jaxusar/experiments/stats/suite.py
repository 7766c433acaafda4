"""Statistics over a task suite's runs x tasks, as rliable defines them (Agarwal et al. 2021, "Deep
Reinforcement Learning at the Edge of the Statistical Precipice", NeurIPS; the ``rliable`` library).

Scores are normalized returns (``normalized_scores``), higher is better, arranged ``[runs, tasks]``, or
``[runs, tasks, points]`` for a sample-efficiency curve. Every run of a task counts once; every task
weighs the same.

Intervals come from rliable's stratified bootstrap (``library.StratifiedBootstrap``, its default
``task_bootstrap=False``): a resample draws, for each task on its own, as many runs as it has, with
replacement, from that task's runs only, so tasks never mix. As in rliable, every entry of the array
draws its own run: for curves that is one draw per (run, task, point), which gives each point's
interval the same distribution as resampling whole curves. An interval at ``level`` is the percentile
interval: ``np.percentile`` (linear interpolation) of the resampled statistic at ``(1 - level) / 2``
and ``1 - (1 - level) / 2``, as ``arch``'s ``conf_int(method="percentile")`` computes it for rliable.

The resamples are drawn all at once with a numpy Generator (in blocks that bound memory), so a seed
gives the same interval on every machine. Defaults, chosen so that a leaderboard's statistics stay a
matter of seconds (5 algorithms x 8 tasks, curves of 50 points: 2 to 3 s with 3 runs, 4 to 9 s with 8,
on the shared 2-core CPU; benchmarks/README.md, "Statistics against rliable"):

* aggregates: ``AGGREGATE_RESAMPLES`` = 50,000, rliable's ``get_interval_estimates`` default;
* performance profiles, probability of improvement and sample-efficiency curves: ``CURVE_RESAMPLES`` =
  2,000, rliable's ``create_performance_profile`` default and the README's for probability of
  improvement (its curves example uses 50,000; at 2,000 a 95% bound's seed-to-seed standard deviation
  is at most about 2% of the interval's width).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import numpy as np
from scipy.stats import trim_mean

AGGREGATE_RESAMPLES = 50_000
CURVE_RESAMPLES = 2_000
_BLOCK = 1 << 22  # entries of resampled scores held at once (32 MiB of float64)

AGGREGATES = ("iqm", "median", "mean", "optimality_gap")


class Estimate(NamedTuple):
    """A point estimate and its percentile bootstrap interval [low, high] (floats, or arrays alike)."""

    point: float | np.ndarray
    low: float | np.ndarray
    high: float | np.ndarray


# -- normalization ----------------------------------------------------------------------------------
def normalized_scores(scores, reference, minimum=None) -> np.ndarray:
    """``(score - minimum) / (reference - minimum)`` per task: 1 at the task's reference optimum or bound.

    scores: raw returns ``[runs, tasks, ...]``; reference: ``[tasks]``, the return of an optimal policy (or
    a bound on it); minimum: ``[tasks]``, the return that should read 0 (rliable's "random" score), 0 when
    omitted, so a score is then return over reference.
    """
    scores = np.asarray(scores, float)
    if scores.ndim < 2:
        raise ValueError(f"scores must be [runs, tasks, ...], got shape {scores.shape}")
    tasks = scores.shape[1]
    reference = np.asarray(reference, float)
    minimum = np.zeros(tasks) if minimum is None else np.asarray(minimum, float)
    if reference.shape != (tasks,) or minimum.shape != (tasks,):
        raise ValueError(f"reference and minimum must be [tasks] = [{tasks}], "
                         f"got {reference.shape} and {minimum.shape}")
    span = reference - minimum
    if np.any(span == 0):
        raise ValueError(f"tasks {np.flatnonzero(span == 0).tolist()}: reference equals minimum, "
                         "nothing to normalize by")
    per_task = (tasks,) + (1,) * (scores.ndim - 2)
    return (scores - minimum.reshape(per_task)) / span.reshape(per_task)


# -- point estimates: scores [..., runs, tasks], leading axes batched ------------------------------
def aggregate_iqm(scores):
    """Interquartile mean of all runs x tasks: the mean of the middle half (25% trimmed each side)."""
    scores = np.asarray(scores, float)
    return trim_mean(scores.reshape(*scores.shape[:-2], -1), 0.25, axis=-1)


def aggregate_median(scores):
    """Median over tasks of each task's mean over runs (rliable's ``aggregate_median``)."""
    return np.median(np.mean(np.asarray(scores, float), axis=-2), axis=-1)


def aggregate_mean(scores):
    """Mean over tasks of each task's mean over runs."""
    return np.mean(np.mean(np.asarray(scores, float), axis=-2), axis=-1)


def aggregate_optimality_gap(scores, gamma: float = 1.0):
    """Mean over runs x tasks of ``max(gamma - score, 0)``: how far below ``gamma`` the scores fall.

    Written as rliable writes it, ``gamma - mean(min(score, gamma))``, the same number to the last bit.
    """
    return gamma - np.mean(np.minimum(np.asarray(scores, float), gamma), axis=(-2, -1))


def score_distribution(scores, taus):
    """Fraction of all runs x tasks with score > tau, per tau: ``[..., runs, tasks] -> [..., len(taus)]``."""
    scores, taus = np.asarray(scores, float), np.asarray(taus, float)
    return np.mean(scores[..., None] > taus, axis=(-3, -2))


def probability_of_improvement(scores_x, scores_y):
    """P(X > Y): per task, the Mann-Whitney U of X over Y divided by ``runs_x * runs_y`` (the fraction
    of run pairs where X scores higher, ties counting 1/2), averaged over tasks.

    scores_x: ``[..., runs_x, tasks]``; scores_y: ``[..., runs_y, tasks]``; leading axes batched.
    """
    x = np.asarray(scores_x, float)[..., :, None, :]
    y = np.asarray(scores_y, float)[..., None, :, :]
    per_task = np.mean((x > y) + 0.5 * (x == y), axis=(-3, -2))
    return np.mean(per_task, axis=-1)


# -- stratified bootstrap ---------------------------------------------------------------------------
def _generator(seed):
    # Anything with Generator.integers passes: benchmarks/rliable_check.py hands in rliable's own
    # (legacy, global) random draws to reproduce its intervals exactly.
    return seed if hasattr(seed, "integers") else np.random.default_rng(seed)


def _blocks(resamples: int, entries: int) -> list[int]:
    """Resamples per block so that a block holds about ``_BLOCK`` entries (``entries`` per resample)."""
    size = max(1, _BLOCK // max(entries, 1))
    return [min(size, resamples - start) for start in range(0, resamples, size)]


def _percentile_interval(resampled: np.ndarray, level: float):
    alpha = (1.0 - level) / 2
    low, high = np.percentile(resampled, [100 * alpha, 100 * (1.0 - alpha)], axis=0)
    return low, high


def _check(scores, ndim: int, what: str) -> np.ndarray:
    scores = np.asarray(scores, float)
    if scores.ndim != ndim or 0 in scores.shape:
        raise ValueError(f"{what} must be a non-empty {ndim}-d array, got shape {scores.shape}")
    return scores


def stratified_bootstrap(statistic: Callable, scores, *, resamples: int = AGGREGATE_RESAMPLES,
                         level: float = 0.95, seed=0, cost: int = 1) -> Estimate:
    """``statistic(scores)`` and its stratified-bootstrap percentile interval (rliable's
    ``get_interval_estimates`` with ``StratifiedBootstrap``).

    scores: ``[runs, tasks, ...]``. statistic maps ``[..., runs, tasks, ...]`` to ``[..., *out]``,
    batched over leading axes (it is called on blocks ``[n, runs, tasks, ...]`` of resamples).
    seed: an int or a numpy Generator. cost: entries the statistic makes per score entry (a block's
    memory bound). Returns arrays shaped like ``statistic(scores)``.
    """
    scores = np.asarray(scores, float)
    if scores.ndim < 2 or 0 in scores.shape:
        raise ValueError(f"scores must be a non-empty [runs, tasks, ...] array, got shape {scores.shape}")
    rng, runs = _generator(seed), scores.shape[0]
    # Each entry keeps its task (and point) and draws a run: the strata are the tasks.
    rest = scores.shape[1:]
    strata = tuple(np.arange(n).reshape((n,) + (1,) * (len(rest) - 1 - i)) for i, n in enumerate(rest))
    resampled = np.concatenate([
        np.asarray(statistic(scores[(rng.integers(0, runs, size=(n, *scores.shape)), *strata)])).reshape(n, -1)
        for n in _blocks(resamples, scores.size * cost)])
    point = statistic(scores)
    low, high = _percentile_interval(resampled, level)
    shape = np.shape(point)
    return Estimate(point, low.reshape(shape)[()], high.reshape(shape)[()])


def aggregates(scores, *, resamples: int = AGGREGATE_RESAMPLES, level: float = 0.95, seed=0,
               gamma: float = 1.0) -> dict[str, Estimate]:
    """IQM, median, mean and optimality gap of scores ``[runs, tasks]``, each with its stratified
    bootstrap interval (one set of resamples for all four)."""
    scores = _check(scores, 2, "scores [runs, tasks]")

    def all_four(s):
        return np.stack([aggregate_iqm(s), aggregate_median(s), aggregate_mean(s),
                         aggregate_optimality_gap(s, gamma)], axis=-1)

    e = stratified_bootstrap(all_four, scores, resamples=resamples, level=level, seed=seed)
    return {name: Estimate(float(e.point[i]), float(e.low[i]), float(e.high[i])) for i, name in enumerate(AGGREGATES)}


def performance_profile(scores, taus, *, resamples: int = CURVE_RESAMPLES, level: float = 0.95,
                        seed=0) -> Estimate:
    """Score distribution: the fraction of runs x tasks with score > tau for each tau, with bootstrap
    bands (rliable's ``create_performance_profile``, ``use_score_distribution=True``).

    scores: ``[runs, tasks]``; taus: ``[T]``. Returns ``Estimate`` of arrays ``[T]``.
    """
    scores = _check(scores, 2, "scores [runs, tasks]")
    taus = np.asarray(taus, float).reshape(-1)
    return stratified_bootstrap(lambda s: score_distribution(s, taus), scores, resamples=resamples,
                                level=level, seed=seed, cost=len(taus))


def iqm_curve(scores, *, resamples: int = CURVE_RESAMPLES, level: float = 0.95, seed=0) -> Estimate:
    """IQM sample-efficiency curve: scores ``[runs, tasks, points]`` (a score at each of ``points``
    budgets, e.g. env steps) -> the IQM over runs x tasks at each point, with its stratified bootstrap
    interval. Returns ``Estimate`` of arrays ``[points]``.
    """
    scores = _check(scores, 3, "scores [runs, tasks, points]")
    return stratified_bootstrap(lambda s: aggregate_iqm(np.moveaxis(s, -1, -3)), scores,
                                resamples=resamples, level=level, seed=seed)


def probabilities_of_improvement(scores: Mapping[str, np.ndarray], pairs: Sequence[tuple[str, str]] | None = None,
                                 *, resamples: int = CURVE_RESAMPLES, level: float = 0.95,
                                 seed=0) -> dict[tuple[str, str], Estimate]:
    """P(X > Y) with its stratified bootstrap interval for each pair (X, Y) of algorithms.

    scores: algorithm -> ``[runs, tasks]`` (same tasks, in the same order; run counts may differ).
    pairs: default every pair in the mapping's order, X before Y; P(Y > X) is 1 - P(X > Y). X's and Y's
    runs are resampled independently, each within each task (rliable's
    ``StratifiedIndependentBootstrap``); the pairs draw one after another from one Generator.
    """
    names = list(scores)
    arrays = {name: _check(scores[name], 2, f"scores[{name!r}] [runs, tasks]") for name in names}
    if len({a.shape[1] for a in arrays.values()}) > 1:
        raise ValueError(f"algorithms have different task counts: { {n: a.shape[1] for n, a in arrays.items()} }")
    pairs = [(x, y) for i, x in enumerate(names) for y in names[i + 1:]] if pairs is None else list(pairs)
    rng, tasks, out = _generator(seed), arrays[names[0]].shape[1], {}
    task = np.arange(tasks)
    for x_name, y_name in pairs:
        x, y = arrays[x_name], arrays[y_name]
        # Per resample, X's run draws then Y's, in one call (the order rliable makes them in).
        high = np.repeat([len(x), len(y)], [x.size, y.size])
        resampled = []
        for n in _blocks(resamples, len(x) * len(y) * tasks):
            runs = rng.integers(0, high, size=(n, high.size))
            ix, iy = runs[:, :x.size].reshape(n, *x.shape), runs[:, x.size:].reshape(n, *y.shape)
            resampled.append(probability_of_improvement(x[ix, task], y[iy, task]))
        low, high = _percentile_interval(np.concatenate(resampled), level)
        out[x_name, y_name] = Estimate(float(probability_of_improvement(x, y)), float(low), float(high))
    return out
