"""``jaxusar train scripted``: the scripted team (``jaxusar/algos/scripted.py``) judged as a learned team is.

Nothing is trained: each trial plays the team's episodes on the judging draws (``judging_keys``) with
its own tie-break key, and ``judge`` scores them:

* fixed victims: every draw is the one start; a trial's team steps against the exact optimum (or the
  lower bound), and whether it is optimal (every victim saved in exactly the reference's steps);
* victims drawn at reset: ``DRAWS`` draws from seed ``DRAW_SEED`` (the benchmark's, the same for every
  algorithm and trial); a trial's **normalized score** is its mean return over the draws divided by the
  clairvoyant optimum's (``planning.clairvoyant_reference``) on the same draws; with the fraction of
  draws with every victim saved and the critical victims saved.

Writes metrics.json (per-trial values and, over trials, the median, the IQM with its 95% bootstrap
interval and the best) and team_episode.png (trial 0's episode on the first draw).
"""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from jaxusar import envs, planning
from jaxusar.envs.render import save_episode_strip
from jaxusar.envs.usar import CRITICAL
from jaxusar.algos import scripted
from jaxusar.config import ExperimentConfig
from jaxusar.experiments.stats import trials as trial_stats

DRAWS, DRAW_SEED = 32, 0


def judging_keys(env, draws: int = DRAWS, seed: int = DRAW_SEED) -> jax.Array:
    """The reset keys a team is judged on: ``draws`` of them where victims are drawn, else the one start."""
    return jax.random.split(jax.random.PRNGKey(seed), draws if env.n_drawn else 1)


def over_trials(values) -> dict:
    """median, IQM with its 95% bootstrap interval, and best (highest) of per-trial scores."""
    x = [float(v) for v in values]
    return {"median": float(np.median(x)), "iqm": trial_stats.iqm(x), "iqm_ci95": trial_stats.bootstrap_ci(x),
            "best": max(x)}


def judge(env, episodes: dict) -> dict:
    """Scores of teams' greedy episodes on ``judging_keys(env)``: ``episodes`` holds arrays
    [trials, draws] of ``return``, ``steps``, ``saved``, ``critical_saved`` (``scripted.rollout``'s keys)."""
    ep = {k: np.asarray(v) for k, v in episodes.items()}
    all_saved = ep["saved"] == env.n_victims
    out = {"mean_return": ep["return"].mean(1).round(4).tolist(),
           "fraction_all_saved": all_saved.mean(1).round(4).tolist(),
           "critical_saved": ep["critical_saved"].mean(1).round(4).tolist(),
           "critical_victims": int(np.sum(env.victim_kind == CRITICAL))}
    if env.n_drawn:
        ref = planning.clairvoyant_reference(env, n_draws=ep["return"].shape[1], seed=DRAW_SEED)
        score = ep["return"].mean(1) / ref["return"]
        out.update(reference=ref["reference"], reference_return=float(ref["return"]),
                   normalized_score=score.round(4).tolist(), normalized=over_trials(score))
    else:
        from jaxusar.experiments.train import reference_metrics

        ref, solved = planning.team_reference(env), all_saved[:, 0]
        steps = np.where(solved, ep["steps"][:, 0], env.horizon)
        out.update(reference_metrics(ref, {"episodes_to_solved": [0 if ok else None for ok in solved],
                                           "best_length": steps}),
                   team_steps=steps.tolist(), optimal=(solved & (steps == ref["steps"])).tolist())
    return out


class Experiment:
    """No trainer: ``finish`` plays and judges the scripted team (``jaxusar.experiments.train``'s interface)."""

    FIGURES = ("team_episode.png",)

    def __init__(self, cfg: ExperimentConfig, keys: jax.Array):
        from jaxusar.experiments.train import all_trial_keys

        # nothing to train: process 0, the one that writes, plays every process's trials (under jax.distributed)
        self.cfg, self.keys = cfg, all_trial_keys(cfg.seed, len(keys) * jax.process_count())
        self.env = envs.make(cfg.env.map, **cfg.env.overrides())
        self.chains = []
        self._played: dict[bytes, dict] = {}

    def play(self, resets: jax.Array) -> dict:
        """Each trial's episodes from the reset keys ``resets``: ``scripted.rollout``'s arrays, [trials, draws].
        Kept per ``resets``: ``finish`` and a benchmark's scoring judge the same draws (the team is fixed)."""
        seen = np.asarray(resets).tobytes()
        if seen not in self._played:
            play = jax.vmap(jax.vmap(lambda r, k: scripted.rollout(self.env, r, k), (0, None)), (None, 0))
            self._played[seen] = jax.device_get(jax.jit(play)(resets, self.keys))
        return self._played[seen]

    def finish(self, out: Path, outcomes: dict, figures: bool = True) -> dict:
        from jaxusar.experiments.train import environment_info

        env, cfg = self.env, self.cfg
        resets = judging_keys(env)
        judged = judge(env, self.play(resets))
        if env.n_drawn:
            n = judged["normalized"]
            line = (f"normalized score over {len(resets)} draws (mean return / the {judged['reference']}'s "
                    f"{judged['reference_return']:.1f}): median {n['median']:.3f}, best {n['best']:.3f}; every "
                    f"victim saved in a median {np.median(judged['fraction_all_saved']):.0%} of the draws")
        else:
            line = (f"team steps {judged['team_steps']} against the {judged['reference']} "
                    f"{judged['optimal_team_steps']}; optimal in {sum(judged['optimal'])} of {len(self.keys)} trials")
        print(f"[scripted] {line}", flush=True)
        if figures:
            shown = jax.device_get(jax.jit(lambda r, k: scripted.rollout(env, r, k, trace=True))(resets[0], self.keys[0]))
            steps = int(shown["steps"])
            save_episode_strip(env, jax.tree.map(lambda x: x[:steps + 1], shown["states"]), out / "team_episode.png",
                               rewards=shown["rewards"][:steps],
                               suptitle=f"the scripted team on {env.layout.name}" + (", draw 0" if env.n_drawn else "")
                               + f": {steps} steps, return {float(shown['return']):g}")
        return {"algorithm": "scripted", "trials": len(self.keys), "draws": len(resets), **judged,
                "env_steps": [0] * len(self.keys), "config": cfg.to_dict(), "config_hash": cfg.hash(),
                "environment": environment_info()}
