"""The suite statistics (``jaxusar.experiments.stats.suite``), rliable's definitions: values by hand on
small arrays, the stratified bootstrap against a plain loop, and what stratification must guarantee.
The comparison with rliable itself is benchmarks/rliable_check.py (rliable is only a [bench] extra)."""

import numpy as np
import pytest
from scipy.stats import mannwhitneyu

from jaxusar.experiments import stats
from jaxusar.experiments.stats import suite

# [runs = 4, tasks = 3]. Sorted: 0.0 0.2 0.2 0.3 0.4 0.4 | 0.6 0.8 0.9 1.0 1.2 1.4.
SCORES = np.array([[0.0, 0.4, 1.0],
                   [0.2, 0.6, 1.2],
                   [0.4, 0.9, 1.4],
                   [0.2, 0.3, 0.8]])


def test_aggregates_by_hand():
    # IQM: 12 scores, drop 3 each side, mean of 0.3 0.4 0.4 0.6 0.8 0.9.
    assert suite.aggregate_iqm(SCORES) == pytest.approx(3.4 / 6)
    # Median of the task means 0.2, 0.55, 1.1 (the median of all 12 scores would be 0.5).
    assert suite.aggregate_median(SCORES) == pytest.approx(0.55)
    assert suite.aggregate_mean(SCORES) == pytest.approx(1.85 / 3)
    # Gap: max(1 - score, 0) sums to 3.2 + 1.8 + 0.2 over the tasks (unclipped it would be 1 - mean).
    assert suite.aggregate_optimality_gap(SCORES) == pytest.approx(5.2 / 12)
    assert suite.aggregate_optimality_gap(SCORES, gamma=0.5) == pytest.approx((0.5 + 0.3 + 0.1 + 0.3 + 0.1 + 0.2) / 12)
    e = stats.aggregates(SCORES, resamples=500)
    assert list(e) == ["iqm", "median", "mean", "optimality_gap"]
    assert e["iqm"].point == pytest.approx(3.4 / 6) and e["median"].point == pytest.approx(0.55)
    for name, (point, low, high) in e.items():
        assert low <= point <= high and low < high, name


def test_iqm_of_eight_runs_of_one_task():
    scores = np.array([[800, 100, 300, 200, 700, 400, 600, 500]], float).T  # [8 runs, 1 task]
    assert suite.aggregate_iqm(scores) == 450  # 300..600


def test_bootstrap_equals_a_loop_over_resamples():
    """The vectorized bootstrap is the plain one: per resample and per task, runs drawn with replacement
    from that task's runs; percentile interval by np.percentile's linear rule at 2.5 and 97.5."""
    scores = np.random.default_rng(3).random((5, 4))
    rng, task = np.random.default_rng(11), np.arange(4)
    resampled = [suite.aggregate_iqm(scores[rng.integers(0, 5, size=(5, 4)), task]) for _ in range(300)]
    low, high = np.percentile(resampled, [2.5, 97.5])
    e = stats.aggregates(scores, resamples=300, seed=np.random.default_rng(11))["iqm"]
    assert e.low == pytest.approx(low, abs=1e-12) and e.high == pytest.approx(high, abs=1e-12)
    assert stats.aggregates(scores, resamples=300, seed=5) == stats.aggregates(scores, resamples=300, seed=5)
    assert stats.aggregates(scores, resamples=300, seed=5) != stats.aggregates(scores, resamples=300, seed=6)


def test_stratified_bootstrap_never_mixes_tasks():
    scores = np.array([[0.3, 0.1], [0.3, 0.9], [0.3, 0.5]])  # task 0: all runs equal
    per_task = stats.stratified_bootstrap(lambda s: np.mean(s, axis=-2), scores, resamples=2000)
    assert per_task.low[0] == per_task.high[0] == 0.3
    assert per_task.low[1] < 0.5 < per_task.high[1]
    # Each task constant over its runs, different across tasks: every resample is the same array, so
    # every interval has zero width (resampling over runs x tasks together would mix the tasks).
    constant = np.tile([0.2, 0.7, 1.3], (6, 1))
    for name, (point, low, high) in stats.aggregates(constant, resamples=2000).items():
        assert low == high == pytest.approx(point), name


def test_probability_of_improvement_by_hand():
    x = np.array([[1.0, 3.0], [2.0, 0.0]])  # [2 runs, 2 tasks]
    y = np.array([[2.0, 1.0], [2.0, 1.0]])
    # Task 0: 1<2, 1<2, 2=2, 2=2 -> 2 ties count 1/2 -> 0.25. Task 1: 3>1 twice, 0<1 twice -> 0.5.
    assert suite.probability_of_improvement(x, y) == pytest.approx(0.375)
    assert suite.probability_of_improvement(y, x) == pytest.approx(0.625)
    # Different run counts, ties: the Mann-Whitney U of X over Y per task / (n m), mean over tasks.
    rng = np.random.default_rng(0)
    x, y = rng.integers(0, 4, (5, 3)).astype(float), rng.integers(0, 4, (3, 3)).astype(float)
    u = [mannwhitneyu(x[:, t], y[:, t], alternative="greater").statistic / 15 for t in range(3)]
    assert suite.probability_of_improvement(x, y) == pytest.approx(np.mean(u))


def test_probability_of_improvement_dominating_and_identical():
    better = SCORES + 2.0
    e = stats.probabilities_of_improvement({"better": better, "worse": SCORES, "same": SCORES}, resamples=1000)
    assert list(e) == [("better", "worse"), ("better", "same"), ("worse", "same")]
    assert tuple(e["better", "worse"]) == (1.0, 1.0, 1.0)  # every resample dominates too
    point, low, high = e["worse", "same"]
    assert point == 0.5 and low < 0.5 < high  # identical, but resampled independently
    only = stats.probabilities_of_improvement({"a": SCORES, "b": better}, pairs=[("b", "a")], resamples=10)
    assert list(only) == [("b", "a")] and only["b", "a"].point == 1.0


def test_performance_profile_by_hand():
    taus = np.array([0.0, 0.2, 0.5, 1.0, 2.0])
    # Scores strictly above each tau: 11 (not the 0.0), 9 (not the 0.2s), 6, 2 (1.2 and 1.4), 0.
    point, low, high = stats.performance_profile(SCORES, taus, resamples=1000)
    np.testing.assert_allclose(point, np.array([11, 9, 6, 2, 0]) / 12)
    fine = stats.performance_profile(SCORES, np.linspace(-0.1, 1.5, 161), resamples=1000)
    for curve in fine:
        assert np.all(np.diff(curve) <= 0)  # non-increasing: the profile and both bands
    assert np.all(fine.low <= fine.point) and np.all(fine.point <= fine.high)
    assert fine.point[0] == 1 and fine.point[-1] == 0


def test_iqm_curve_of_constant_runs_has_zero_width():
    per_task_point = np.linspace(0, 1, 3 * 7).reshape(3, 7)  # [tasks, points], the same in every run
    curve = stats.iqm_curve(np.broadcast_to(per_task_point, (5, 3, 7)), resamples=2000)
    np.testing.assert_allclose(curve.low, curve.point)
    np.testing.assert_allclose(curve.high, curve.point)
    from scipy.stats import trim_mean
    np.testing.assert_allclose(curve.point, trim_mean(np.repeat(per_task_point, 5, axis=0), 0.25, axis=0))
    noisy = stats.iqm_curve(np.random.default_rng(1).random((5, 3, 7)), resamples=500)
    assert noisy.point.shape == noisy.low.shape == (7,) and np.all(noisy.low < noisy.high)


def test_normalized_scores():
    raw = np.array([[50.0, -10.0], [100.0, 30.0]])
    np.testing.assert_allclose(stats.normalized_scores(raw, [100.0, 40.0]), [[0.5, -0.25], [1.0, 0.75]])
    # With a minimum (rliable's "random" score): (score - minimum) / (reference - minimum).
    np.testing.assert_allclose(stats.normalized_scores(raw, [100.0, 40.0], [0.0, -10.0]), [[0.5, 0.0], [1.0, 0.8]])
    curves = stats.normalized_scores(np.ones((2, 2, 3)), [2.0, 4.0])
    np.testing.assert_allclose(curves[0], [[0.5] * 3, [0.25] * 3])
    with pytest.raises(ValueError, match="reference equals minimum"):
        stats.normalized_scores(raw, [100.0, -10.0], [0.0, -10.0])
    with pytest.raises(ValueError, match=r"\[tasks\]"):
        stats.normalized_scores(raw, [100.0, 40.0, 1.0])


def test_bad_shapes_are_one_line_errors():
    with pytest.raises(ValueError, match=r"\[runs, tasks\]"):
        stats.aggregates(np.ones(4))
    with pytest.raises(ValueError, match=r"\[runs, tasks, points\]"):
        stats.iqm_curve(np.ones((4, 2)))
    with pytest.raises(ValueError, match="different task counts"):
        stats.probabilities_of_improvement({"a": np.ones((2, 3)), "b": np.ones((2, 4))})
