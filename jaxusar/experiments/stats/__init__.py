"""Statistics of results.

* ``trials``: over one task's trials of episodes-to-optimal, where a trial may never get there (the
  paper's Table II: best, median, IQM with its bootstrap interval, fraction optimal).
* ``suite``: over a task suite's runs x tasks of normalized scores, as rliable defines them (aggregate
  IQM, median, mean, optimality gap; performance profiles; probability of improvement; IQM
  sample-efficiency curves; all with stratified bootstrap intervals).

Both are importable from here, as ``jaxusar.experiments.stats`` was one module before.
"""

from jaxusar.experiments.stats.suite import (AGGREGATE_RESAMPLES, AGGREGATES, CURVE_RESAMPLES, Estimate,
                                             aggregate_iqm, aggregate_mean, aggregate_median,
                                             aggregate_optimality_gap, aggregates, iqm_curve,
                                             normalized_scores, performance_profile,
                                             probabilities_of_improvement, probability_of_improvement,
                                             score_distribution, stratified_bootstrap)
from jaxusar.experiments.stats.trials import bootstrap_ci, in_words, iqm, summarize

__all__ = ["AGGREGATE_RESAMPLES", "AGGREGATES", "CURVE_RESAMPLES", "Estimate", "aggregate_iqm", "aggregate_mean",
           "aggregate_median", "aggregate_optimality_gap", "aggregates", "bootstrap_ci", "in_words", "iqm",
           "iqm_curve", "normalized_scores", "performance_profile", "probabilities_of_improvement",
           "probability_of_improvement", "score_distribution", "stratified_bootstrap", "summarize"]
