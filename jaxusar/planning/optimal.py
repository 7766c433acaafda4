"""The team's exact optimum from the reset state, by the joint search (``search.py``): fewest steps to
triage every victim, or, where critical victims expire, the highest return.

On part 1's maps the fewest steps come from the plain breadth-first search (its states, plans and limits
are those benchmarks/README.md measured). Elsewhere (rubble, engineers, multi-step triage, critical
victims) a third agent or the rubble bits multiply the joint states, so the search cuts every state that
cannot finish within a step limit (``bounds.StateBounds``: no victim's steps are overestimated), starting
at the lower bound and raising the limit by one until a plan is found: the first found is the optimum.
"""

from __future__ import annotations

import numpy as np

from jaxusar.envs.layout import CRITICAL
from jaxusar.envs.usar import TURN_LEFT, EnvState, USAREnv
from jaxusar.planning.bounds import (INF, StateBounds, _deadlines, _require_fixed, _worth, episode_lower_bound,
                                     team_lower_bound)
from jaxusar.planning.search import _Codec, _all_triaged, _check_size, _layered, _search, Unreachable


def optimal_team_steps(env: USAREnv, max_states: int = 20_000_000) -> int:
    """Fewest joint primitive steps for the team to triage every victim from the reset state.

    Exact: searches the joint state of all agents, so agents blocking each other, rubble cleared by the
    engineers, and triage shared between medics are accounted for. Ignores the horizon (an optimum above
    it means the map cannot be solved within it). Where critical victims expire, the victims must be
    saved before they do (Unreachable when some cannot be), and the optimum in the return sense is
    ``optimal_team_return``.
    """
    _check_size(env, max_states)
    return _fewest_steps(env, max_states, record=False)[0]


def optimal_team_plan(env: USAREnv, max_states: int = 20_000_000) -> np.ndarray:
    """One shortest joint plan from the reset state: int32[T, n_agents] actions, T = ``optimal_team_steps(env)``.

    Replaying it through ``env.step`` triages every victim at step T (when T <= horizon). Among the many
    optimal plans it returns a fixed one; agents with slack may spend it on no-op turns or triages.
    """
    _check_size(env, max_states)
    return _fewest_steps(env, max_states, record=True)[1]


def _fewest_steps(env: USAREnv, max_states: int, record: bool, start: EnvState | None = None,
                  fixed: USAREnv | None = None, stats: dict | None = None):
    """(steps, plan) from ``start`` (default: the reset state). ``fixed``: the map with ``start``'s victims
    fixed (``reference.fixed_victims``; default ``env``), where the cut's bounds come from."""
    if start is None:
        _require_fixed(env, "the exact search")
        start = env.initial_state()
    if env.part1:
        return _search(env, start, _all_triaged, max_states, record, stats)
    fixed = env if fixed is None else fixed
    bounds = StateBounds(fixed)
    limit = max(team_lower_bound(fixed), int(bounds.steps_to_go(0, _Codec(env).of(env.complete(start)))[0]))
    while True:
        cut = [False]  # did the limit (not a lost victim) cut some state?

        def prune(depth, states):
            to_go = bounds.steps_to_go(depth, states)
            keep = depth + to_go <= limit
            cut[0] |= bool(np.any(~keep & (to_go < INF)))
            return keep

        try:
            return _search(env, start, _all_triaged, max_states, record, stats, prune)
        except Unreachable:
            if not cut[0]:
                raise
            limit += 1


def return_search_exact(env: USAREnv) -> bool:
    """Whether the highest-return search is exact on ``env``: it keeps each state's first visit, which is
    enough when arriving earlier never hurts (step_penalty <= 0, rewards >= 0)."""
    return env.step_penalty <= 0 and env.triage_reward >= 0 and env.critical_reward >= 0


def _check_return_rules(env: USAREnv) -> None:
    if not return_search_exact(env):
        raise ValueError(f"the highest-return search needs step_penalty <= 0 and rewards >= 0; {env.layout.name!r} has "
                         f"step_penalty={env.step_penalty}, triage_reward={env.triage_reward}, "
                         f"critical_reward={env.critical_reward}")


def optimal_team_return(env: USAREnv, max_states: int = 20_000_000) -> dict:
    """The highest undiscounted episode return from the reset state, and among plans reaching it the fewest
    steps: "optimal" where critical victims expire, since saving a critical victim may be worth more than
    triaging regular ones sooner.

    Return = triage_reward x regular victims triaged + critical_reward x critical ones + step_penalty x
    steps; the episode ends when every victim is triaged or dead, or at the horizon (DESIGN.md contract
    part 2). Exact: the joint search in time layers (a state's dead victims follow from its triaged flags
    and its layer), cutting the states whose best conceivable return (``bounds.StateBounds``: the victims
    still savable in time) cannot beat the best episode found so far. Needs step_penalty <= 0 and rewards
    >= 0: then arriving at a state earlier never hurts, which makes first visits enough, counting for
    each state the episodes that wait there (turning) until they end by themselves. Where no victim
    expires, that is every victim triaged in ``optimal_team_steps`` (when within the horizon).

    Returns ``{"return": float, "steps": int, "plan": int32[steps, n_agents], "triaged": bool[V]}``;
    replaying ``plan`` through ``env.step`` ends the episode at its last step with that return.
    """
    _require_fixed(env, "optimal_team_return")
    _check_size(env, max_states)
    return _best_return(env, env.initial_state(), env, max_states)


def _best_return(env: USAREnv, start: EnvState, fixed: USAREnv, max_states: int, stats: dict | None = None) -> dict:
    """``optimal_team_return`` from ``start`` (t = 0; drawn victims in it). ``fixed`` is the map with these
    victims fixed (``reference.fixed_victims``), where the bounds come from, so every draw of a map with
    victims drawn at reset shares one compile of the search.

    Rounds: a round keeps only the states that may still triage victims worth ``level`` or more, and
    the next round lowers ``level`` to the most that a cut state might have triaged, until no episode
    triaging less can beat the best found (it also lasts ``episode_lower_bound`` steps at least).
    """
    _check_return_rules(env)
    worth = _worth(env)
    if not env.expires:  # nothing dies: everyone triaged in the fewest steps, if the horizon allows
        try:
            steps, plan = _fewest_steps(env, max_states, True, start, fixed, stats)
        except Unreachable:
            steps = None
        if steps is not None and steps <= env.horizon:
            return {"return": float(worth.sum() + env.step_penalty * steps), "steps": int(steps), "plan": plan,
                    "triaged": np.ones(env.n_victims, bool)}
    bounds, deadline = StateBounds(fixed), _deadlines(env)
    critical = env.victim_kind == CRITICAL
    scale = 1e-9 * max(1.0, float(np.abs(worth).sum()), abs(env.step_penalty) * env.horizon)  # float ties
    shortest = episode_lower_bound(fixed)
    best = {"return": -np.inf, "steps": env.horizon + 1}

    def better(value, steps):
        return (value > best["return"] + scale) | ((value >= best["return"] - scale) & (steps < best["steps"]))

    def hopes(t, s):
        """(ended, rewards so far, worth hope, return hope) of the layer at time t."""
        dead = critical & ~s.triaged & (t >= env.critical_expires) if env.expires else np.zeros_like(s.triaged)
        rewards = s.triaged @ worth
        ended = (s.triaged | dead).all(1) | (t >= env.horizon)
        savable = ~s.triaged & ~dead & (t + bounds.victim_steps(t, s) <= deadline)
        most = rewards + (savable * worth).sum(1)
        return ended, rewards, most, most + env.step_penalty * (t + 1)

    def ending(t, s, ended):
        """int[N]: when an episode at each state ends if it triages no one more (the agents turn): now if it
        has ended, else when the critical victims left die (if only they are left), else at the horizon.
        A state a later layer reaches again is not expanded again: this keeps its episodes that wait."""
        if not env.expires:
            return np.where(ended, t, env.horizon)
        only_critical = (s.triaged | critical).all(1)
        return np.where(ended, t, np.where(only_critical, min(env.horizon, env.critical_expires), env.horizon))

    level = float(hopes(0, _Codec(env).of(env.complete(start)))[2][0])
    while True:
        below = [-np.inf]  # the most a state cut for its level might have triaged

        def on_layer(t, s, plan_to):
            ended, rewards, most, hope = hopes(t, s)
            steps = ending(t, s, ended)
            value = rewards + env.step_penalty * steps
            top = value >= value.max() - scale
            i = int(np.flatnonzero(top)[np.argmin(steps[top])])  # the best, then the fewest steps, then first
            if better(value[i], steps[i]):
                wait = np.full((steps[i] - t, env.n_agents), TURN_LEFT, np.int32)
                best.update({"return": float(value[i]), "steps": int(steps[i]),
                             "plan": np.concatenate([plan_to(i), wait]), "triaged": s.triaged[i].copy()})
            alive = ~ended & better(hope, t + 1)
            low = alive & (most < level - scale)
            if low.any():
                below[0] = max(below[0], float(most[low].max()))
            return alive & ~low

        _layered(env, start, on_layer, max_states, record=True, stats=stats)
        if below[0] == -np.inf:  # nothing was cut for its level: the search was complete
            return best
        beaten = below[0] + env.step_penalty * shortest
        if best["return"] > beaten + scale or (best["return"] >= beaten - scale and best["steps"] <= shortest):
            return best
        level = below[0]
