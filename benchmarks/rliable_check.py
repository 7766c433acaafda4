"""Each of jaxusar's suite statistics against rliable itself, on fixed score arrays.

``jaxusar.experiments.stats.suite`` computes rliable's statistics with numpy/scipy alone; rliable is
only a ``[bench]`` extra. For each function this prints three comparisons with rliable 1.2:

* point estimates: the largest |ours - rliable|; must be float rounding (<= 1e-12);
* intervals from the same random draws: rliable draws its resamples from numpy's legacy global
  RandomState (``np.random.choice``, it takes no Generator), so ours are handed an adapter on a
  RandomState with the same seed. Same draws, same statistic, same percentile rule: the bounds must
  agree to float rounding (<= 1e-12);
* intervals from independent draws (ours: a numpy Generator), the same number of resamples: the
  largest |ours - rliable| beside the seed-to-seed standard deviation of our bounds over 10 seeds
  (Monte-Carlo error); every bound must lie within 6 * sqrt(2) sd, plus one step of the statistic
  where it moves in steps (profiles, probability of improvement), of rliable's.

normalized_scores has no rliable function (rliable's notebooks normalize inline, (score - random) /
(human - random)); it is checked against that formula.

    .venv/bin/pip install -e '.[bench]'   # or: .venv/bin/pip install 'rliable>=1.2,<1.3' 'pandas<3'
    python benchmarks/rliable_check.py
"""

from __future__ import annotations

import platform
import sys
import time
from importlib.metadata import version

import numpy as np
import scipy
from rliable import library as rly
from rliable import metrics

from jaxusar.experiments.stats import suite

AGGREGATE_REPS, CURVE_REPS, SEEDS = 50_000, 2_000, 10
RUNS, TASKS, POINTS = {"A": 8, "B": 8, "C": 5}, 10, 20
TAUS = np.linspace(0.0, 1.25, 51)


class LegacyDraws:
    """rliable's random draws (legacy RandomState, seeded like ``np.random.seed``) behind Generator.integers."""

    def __init__(self, seed: int):
        self.state = np.random.RandomState(seed)

    def integers(self, low, high, size):
        return self.state.randint(low, high, size)


def draws(seed: int, legacy: bool):
    """Our functions' seed: an int (a fresh Generator), or rliable's draws, freshly seeded per call."""
    return LegacyDraws(seed) if legacy else seed


def fixed_scores() -> tuple[dict, dict]:
    """Normalized-like scores [runs, tasks] per algorithm (on a 0.05 grid, so there are ties; some
    above 1, so the optimality gap clips), and curves [runs, tasks, points]."""
    rng = np.random.default_rng(2021)
    level = {"A": 0.75, "B": 0.6, "C": 0.65}
    final = {k: np.round(np.clip(rng.normal(level[k], 0.25, (n, TASKS)), 0, 1.3) * 20) / 20 for k, n in RUNS.items()}
    growth = 1 - np.exp(-np.linspace(0.2, 4, POINTS) * rng.uniform(0.5, 2, (8, TASKS, 1)))
    curves = growth * rng.uniform(0.4, 1.2, (8, TASKS, 1)) + rng.normal(0, 0.05, (8, TASKS, POINTS))
    return final, {"A": curves}


def rliable_aggregates(x):
    return np.array([metrics.aggregate_iqm(x), metrics.aggregate_median(x), metrics.aggregate_mean(x),
                     metrics.aggregate_optimality_gap(x)])


def rliable_curve(x):  # as rliable's README writes the IQM sample-efficiency curve
    return np.array([metrics.aggregate_iqm(x[..., point]) for point in range(x.shape[-1])])


def ours_and_rliable(final: dict, curves: dict):
    """name -> (ours(seed, legacy) -> {key: (point, low, high)}, rliable(seed) -> same, resamples, step).

    Each call seeds once per call of rliable's function: per algorithm, except for probability of
    improvement, where one ``get_interval_estimates`` call takes all pairs from one stream.
    """
    n = {k: v.size for k, v in final.items()}

    def agg_ours(seed, legacy=False):
        return {k: np.array([tuple(e) for e in suite.aggregates(v, resamples=AGGREGATE_REPS, seed=draws(seed, legacy)
                                                                ).values()]).T for k, v in final.items()}

    def agg_rliable(seed):
        out = {}
        for k, v in final.items():  # one seeding per algorithm, as ours starts one Generator per call
            np.random.seed(seed)
            point, ci = rly.get_interval_estimates({k: v}, rliable_aggregates, reps=AGGREGATE_REPS)
            out[k] = np.vstack([point[k], ci[k]])
        return out

    def profile_ours(seed, legacy=False):
        return {k: np.array(suite.performance_profile(v, TAUS, resamples=CURVE_REPS, seed=draws(seed, legacy)))
                for k, v in final.items()}

    def profile_rliable(seed):
        out = {}
        for k, v in final.items():
            np.random.seed(seed)
            point, ci = rly.create_performance_profile({k: v}, TAUS, reps=CURVE_REPS)
            out[k] = np.vstack([point[k], ci[k]])
        return out

    def poi_ours(seed, legacy=False):
        return {f"{x}>{y}": np.array(e) for (x, y), e in
                suite.probabilities_of_improvement(final, resamples=CURVE_REPS, seed=draws(seed, legacy)).items()}

    def poi_rliable(seed):
        names = list(final)
        pairs = {f"{x}>{y}": (final[x], final[y]) for i, x in enumerate(names) for y in names[i + 1:]}
        np.random.seed(seed)  # all pairs from one stream, in order, as ours
        point, ci = rly.get_interval_estimates(pairs, metrics.probability_of_improvement, reps=CURVE_REPS)
        return {k: np.concatenate([[point[k]], ci[k].ravel()]) for k in pairs}

    def curve_ours(seed, legacy=False):
        return {k: np.array(suite.iqm_curve(v, resamples=CURVE_REPS, seed=draws(seed, legacy)))
                for k, v in curves.items()}

    def curve_rliable(seed):
        out = {}
        for k, v in curves.items():
            np.random.seed(seed)
            point, ci = rly.get_interval_estimates({k: v}, rliable_curve, reps=CURVE_REPS)
            out[k] = np.vstack([point[k], ci[k]])
        return out

    names = list(RUNS)
    poi_step = max(1 / (2 * RUNS[x] * RUNS[y] * TASKS) for i, x in enumerate(names) for y in names[i + 1:])
    return {
        "aggregates (IQM, median, mean, gap)": (agg_ours, agg_rliable, AGGREGATE_REPS, 0.0),
        f"performance profile ({len(TAUS)} taus)": (profile_ours, profile_rliable, CURVE_REPS, 1 / min(n.values())),
        "probability of improvement (3 pairs)": (poi_ours, poi_rliable, CURVE_REPS, poi_step),
        f"IQM curve ({POINTS} points)": (curve_ours, curve_rliable, CURVE_REPS, 0.0),
    }


def timed(f, *args):
    start = time.perf_counter()
    out = f(*args)
    return out, time.perf_counter() - start


def stack(d: dict) -> np.ndarray:
    """{key: [point, low, high] x ...} -> [3, everything]."""
    return np.concatenate([np.asarray(v, float).reshape(3, -1) for _, v in sorted(d.items())], axis=1)


def defaults_time(runs: int, tasks: int = 8, algorithms: int = 5, points: int = 50) -> float:
    """Seconds for everything a leaderboard needs, at the default resamples: aggregates and an IQM
    curve per algorithm, a profile over 101 taus per algorithm, every pair's probability of improvement."""
    rng = np.random.default_rng(0)
    final = {f"alg{i}": rng.random((runs, tasks)) for i in range(algorithms)}
    start = time.perf_counter()
    for k, v in final.items():
        suite.aggregates(v)
        suite.performance_profile(v, np.linspace(0, 1.25, 101))
        suite.iqm_curve(rng.random((runs, tasks, points)))
    suite.probabilities_of_improvement(final)
    return time.perf_counter() - start


def main() -> int:
    final, curves = fixed_scores()
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), "?")
    print(f"rliable {version('rliable')}, arch {version('arch')}, numpy {np.__version__}, scipy {scipy.__version__}, "
          f"python {platform.python_version()}, {cpu}")
    print(f"scores: runs {RUNS} x {TASKS} tasks; curves 8 x {TASKS} x {POINTS}; seed 0\n")

    raw = np.random.default_rng(7).uniform(-50, 100, (4, 3))
    reference, random_score = np.array([100.0, 80.0, 120.0]), np.array([-50.0, -20.0, 0.0])
    formula = (raw - random_score) / (reference - random_score)
    norm_err = np.max(np.abs(suite.normalized_scores(raw, reference, random_score) - formula))
    print(f"normalized_scores vs (score - random) / (reference - random): max |diff| {norm_err:.1e}\n")

    failed = norm_err > 1e-12
    print("| function | resamples | point: max abs diff | same draws: max abs diff | independent draws: max abs diff "
          "| ours' seed-to-seed sd (max) | interval width (median) | ours s | rliable s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, (ours, theirs, reps, step) in ours_and_rliable(final, curves).items():
        ref, t_rliable = timed(lambda: stack(theirs(0)))
        same = stack(ours(0, legacy=True))
        own, t_ours = timed(lambda: stack(ours(0)))
        spread = np.std([stack(ours(seed))[1:] for seed in range(1, SEEDS + 1)], axis=0, ddof=1)
        d_point = np.max(np.abs(own[0] - ref[0]))
        d_same = np.max(np.abs(same[1:] - ref[1:]))
        d_indep = np.abs(own[1:] - ref[1:])
        ok = d_point <= 1e-12 and d_same <= 1e-12 and np.all(d_indep <= 6 * np.sqrt(2) * spread + step + 1e-12)
        failed |= not ok
        width = np.median(ref[2] - ref[1])
        print(f"| {name} | {reps:,} | {d_point:.1e} | {d_same:.1e} | {d_indep.max():.4f} | {spread.max():.4f} "
              f"| {width:.3f} | {t_ours:.2f} | {t_rliable:.2f} |" + ("" if ok else " **FAIL**"))
    print("\n" + ("FAIL" if failed else "all agree"))
    for runs in (3, 8):
        print(f"defaults ({suite.AGGREGATE_RESAMPLES:,} / {suite.CURVE_RESAMPLES:,} resamples), 5 algorithms x 8 "
              f"tasks x {runs} runs, curves of 50 points: {defaults_time(runs):.1f} s for all statistics")
    return int(failed)


if __name__ == "__main__":
    sys.exit(main())
