"""What teams are measured against on every map: ``team_reference`` (fixed victims: the exact optimum where
the joint search is in reach, else a bound) and ``clairvoyant_reference`` (victims drawn at reset: per draw
of a fixed sample, the best a team could do knowing where the victims are).
"""

from __future__ import annotations

import copy
import dataclasses

import jax
import numpy as np

from jaxusar.envs.layout import HEADER_KEYS
from jaxusar.envs.usar import USAREnv
from jaxusar.planning.bounds import episode_lower_bound, team_lower_bound, team_return_bound
from jaxusar.planning.optimal import _best_return, optimal_team_return, optimal_team_steps, return_search_exact
from jaxusar.planning.search import _check_size, joint_states_bound

# the joint-state bound up to which training and `jaxusar demo` run the exact search: two_rooms 1.2e6; past
# it the search takes minutes and gigabytes (benchmarks/README.md, "The exact optimum's limits")
SEARCH_MAX_BOUND = 50_000_000
# the same for maps with part 2's features, whose search cuts the states that cannot finish in time
# (optimal.py): two_rooms_rubble (3 agents, 2 rubble cells) has 2.5e9 joint states; the search visits 9.5e4
PRUNED_SEARCH_MAX_BOUND = 10_000_000_000
# the states one draw's exact search may visit in clairvoyant_reference before it settles for the bound
CLAIRVOYANT_MAX_STATES = 2_000_000


def in_reach(env: USAREnv) -> bool:
    """Whether the reference runs the exact joint search on ``env`` (fixed victims): its joint-state bound is
    at most ``SEARCH_MAX_BOUND`` on part 1's maps, ``PRUNED_SEARCH_MAX_BOUND`` elsewhere (the search itself
    still stops at its ``max_states``)."""
    limit = SEARCH_MAX_BOUND if env.part1 else PRUNED_SEARCH_MAX_BOUND
    return not env.n_drawn and joint_states_bound(env) <= limit


_REFERENCES: dict[tuple, dict] = {}  # team_reference's answers in this process (a benchmark plans a map per run)


def _env_key(env: USAREnv, *args) -> tuple:
    """What a reference depends on: the env's settings (its repr) and every static array of its layout."""
    arrays = (env.blocked, env.victim_pos, env.victim_kind, env.roles, env.layout.agent_start, env.layout.rubble,
              env.layout.random_cells, env.graph.cell_region)
    return (repr(env), *(np.asarray(a).tobytes() + str(np.shape(a)).encode() for a in arrays), *args)


def team_reference(env: USAREnv, max_states: int = 20_000_000) -> dict:
    """``_team_reference``, remembered per env (its settings and static arrays) in this process: the
    searches take seconds to minutes, and every algorithm of a benchmark or a reproduction asks for them."""
    key = _env_key(env, max_states)
    if key not in _REFERENCES:
        _REFERENCES[key] = _team_reference(env, max_states)
    return copy.deepcopy(_REFERENCES[key])


def _team_reference(env: USAREnv, max_states: int = 20_000_000) -> dict:
    """What teams on ``env`` are measured against.

    Fixed victims: ``steps``, the exact optimum where the joint search is in reach (``in_reach``;
    ``reference: "optimum"``), else ``team_lower_bound`` (``reference: "lower bound"``; a test that takes
    that many steps is optimal, proven by the bound, and longer ones are judged by their gap); and
    ``lower_bound`` itself, for the optimality gap (team steps / lower bound) on every map.

    Where critical victims expire, "optimal" means the highest undiscounted return (rewards of the victims
    triaged + step_penalty x steps; the episode ends when every victim is triaged or dead, or at the
    horizon), and among equal returns the fewest steps (``optimal_team_return``): ``return`` is that
    return (``return_reference: "optimum"``) or, out of reach, ``team_return_bound`` (``"upper bound"``),
    ``steps`` the best-return episode's length (or ``episode_lower_bound``), ``lower_bound`` the episode
    lower bound. (With step_penalty 0 and every victim savable, the best return saves everyone in the
    fewest steps, so ``steps`` is ``optimal_team_steps``.)

    Victims drawn at reset: ``clairvoyant_reference(env)``, plus ``steps`` and ``lower_bound``, the least
    over its draws (of the best-return episode's steps where exact, else of the episode lower bound).
    """
    if env.n_drawn:
        ref = clairvoyant_reference(env, max_states=min(max_states, CLAIRVOYANT_MAX_STATES))
        steps = [s if s is not None else b for s, b in zip(ref["draw_steps"], ref["draw_lower_bounds"])]
        return {**ref, "steps": int(min(steps)), "lower_bound": int(min(ref["draw_lower_bounds"]))}
    if env.expires:
        lower = episode_lower_bound(env)
        ref = {"steps": lower, "reference": "lower bound", "lower_bound": lower,
               "return": team_return_bound(env), "return_reference": "upper bound"}
        if in_reach(env) and return_search_exact(env):
            try:
                best = optimal_team_return(env, max_states)
                ref.update(steps=best["steps"], reference="optimum", **{"return": best["return"]},
                           return_reference="optimum")
            except MemoryError:  # the search passed max_states
                pass
        return ref
    bound = team_lower_bound(env)
    if in_reach(env):
        try:
            return {"steps": optimal_team_steps(env, max_states), "reference": "optimum", "lower_bound": bound}
        except MemoryError:  # the search passed max_states
            pass
    return {"steps": bound, "reference": "lower bound", "lower_bound": bound}


def fixed_victims(env: USAREnv, victim_pos) -> USAREnv:
    """``env`` with its victims fixed at ``victim_pos`` int[n_victims, 2] (a draw: ``state.victim_pos``):
    the same map, settings, victim kinds and index order, nothing drawn at reset."""
    header = {k: v for k, v in env.layout.header.items() if k != "random_victims"}
    layout = dataclasses.replace(env.layout, victim_pos=np.asarray(victim_pos, np.int32).reshape(-1, 2),
                                 victim_kind=np.asarray(env.victim_kind), random_cells=np.zeros((0, 2), np.int32),
                                 header=header)
    settings = {k: getattr(env, k) for k in HEADER_KEYS if k != "random_victims"}
    return USAREnv(layout, horizon=env.horizon, triage_reward=env.triage_reward, step_penalty=env.step_penalty,
                   start_dir=env.start_dir, **settings)


def clairvoyant_reference(env: USAREnv, n_draws: int = 32, seed: int = 0,
                          max_states: int = CLAIRVOYANT_MAX_STATES) -> dict:
    """``_clairvoyant_reference``, remembered per env and arguments in this process (as ``team_reference``)."""
    key = _env_key(env, "clairvoyant", n_draws, seed, max_states)
    if key not in _REFERENCES:
        _REFERENCES[key] = _clairvoyant_reference(env, n_draws, seed, max_states)
    return copy.deepcopy(_REFERENCES[key])


def _clairvoyant_reference(env: USAREnv, n_draws: int = 32, seed: int = 0,
                           max_states: int = CLAIRVOYANT_MAX_STATES) -> dict:
    """The clairvoyant reference of a map whose victims are drawn at reset: over a fixed sample of draws, the
    mean of the best undiscounted return a team could get knowing where the victims are.

    The draws are ``env.initial_state(key)`` for ``key`` in ``jax.random.split(jax.random.PRNGKey(seed),
    n_draws)``: the same for every call with this seed, and apart from any training seed. Per draw, the
    env with those victims fixed (``fixed_victims``): the exact highest return (``optimal_team_return``;
    "optimal" as in ``team_reference``) where the joint search is in reach (``in_reach``, at most
    ``max_states`` states), else ``team_return_bound``, a return no policy can beat (the victim sets the
    relaxed medics, alone and with rubble as floor, triage in time: regular victims within the horizon,
    critical ones before they expire). Either way no policy under partial observation can beat it on
    that draw: it knows what the policy must find. A map with fixed victims has one draw, its own victims:
    the reference is then its highest return (``optimal_team_return``), exact or bounded.

    Returns ``{"reference": "clairvoyant optimum" | "clairvoyant bound" (a bound as soon as one draw is),
    "return": the mean over the draws, "returns": [per draw], "exact": [per draw], "draw_steps": [the
    best-return episode's steps per draw, None where bounded], "draw_lower_bounds": [episode_lower_bound per
    draw], "n_draws", "seed"}``.
    """
    if env.n_drawn:
        keys = jax.random.split(jax.random.PRNGKey(seed), n_draws)
        starts = jax.vmap(env.initial_state)(keys)
    else:  # one draw: the map's own victims
        n_draws, starts = 1, jax.tree.map(lambda x: x[None], env.initial_state())
    returns, exact, steps, lower = [], [], [], []
    for k in range(n_draws):
        start = jax.tree.map(lambda x: x[k], starts)
        fixed = fixed_victims(env, np.asarray(start.victim_pos))
        best = None
        if in_reach(fixed) and return_search_exact(env):
            try:
                _check_size(fixed, max_states)
                best = _best_return(env, start, fixed, max_states)
            except MemoryError:  # past max_states (SearchTooLarge too): settle for the bound
                best = None
        returns.append(best["return"] if best else team_return_bound(fixed))
        exact.append(best is not None)
        steps.append(int(best["steps"]) if best else None)
        lower.append(episode_lower_bound(fixed))
    return {"reference": "clairvoyant optimum" if all(exact) else "clairvoyant bound",
            "return": float(np.mean(returns)), "returns": [float(r) for r in returns], "exact": exact,
            "draw_steps": steps, "draw_lower_bounds": lower, "n_draws": int(n_draws), "seed": int(seed)}
