"""A scripted team: the hand-written heuristic every learned team must beat (no learning).

It acts on what the team may know and nothing more: with ``observation: view`` the cells the team has
seen (``EnvState.seen``) and the cells next to an agent; with ``full`` the whole state, as the learners'
observation is. Each step, every agent follows the shortest known route (unseen cells count as floor;
walls, victims and known rubble as blocked) to its target:

* a medic to the nearest known living untriaged critical victim, else the nearest known untriaged victim,
  else the nearest unseen cell (search); it triages a victim it faces until the victim is saved;
* an engineer to the nearest known rubble, which it clears, else the nearest unseen cell.

An agent whose way forward is held by another agent turns at random (one key per team), so that two
agents meeting in a one-wide corridor do not block each other for ever. The rules apply on every map the
layout accepts (the one they could not serve, engineers only, it refuses: "victims but no medic").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxusar.envs.usar import CRITICAL, DIR_DELTA, ENGINEER, FORWARD, TRIAGE, TURN_LEFT, TURN_RIGHT, EnvState, USAREnv

ALGORITHM = "scripted"
EXPERIMENT = "jaxusar.experiments.scripted"
DESCRIPTION = "A hand-written team (no learning) that sees what the learners see: the bar every learned team must clear."

FAR = 1 << 20  # the distance of a cell with no known route to a target


def distance_to(targets: jax.Array, passable: jax.Array) -> jax.Array:
    """int32[H, W]: moves from each cell to the nearest ``targets`` cell (0 on one) over ``passable``
    cells, FAR where there is no such route. A target need not be passable: a victim or rubble is
    reached by standing next to it."""
    start = jnp.where(targets, 0, FAR)

    def relax(carry):
        dist, _ = carry
        pad = jnp.pad(dist, 1, constant_values=FAR)
        near = jnp.minimum(jnp.minimum(pad[:-2, 1:-1], pad[2:, 1:-1]), jnp.minimum(pad[1:-1, :-2], pad[1:-1, 2:]))
        new = jnp.where(targets, 0, jnp.where(passable, jnp.minimum(dist, near + 1), FAR))
        return new, jnp.any(new != dist)

    return jax.lax.while_loop(lambda c: c[1], relax, (start, jnp.array(True)))[0]


def act(env: USAREnv, state: EnvState, key: jax.Array) -> jax.Array:
    """int32[n_agents]: the scripted team's joint action in ``state`` (module doc)."""
    state = env.complete(state)
    height, width = env.height, env.width
    blocked = jnp.asarray(env.blocked)
    near_agent = jnp.zeros((height, width), bool)
    for delta in ((0, 0), *map(tuple, DIR_DELTA)):  # the cells next to an agent: in its view whatever its mode
        cell = jnp.clip(state.agent_pos + jnp.asarray(delta), 0, jnp.array([height - 1, width - 1]))
        near_agent = near_agent.at[cell[:, 0], cell[:, 1]].set(True)
    known = (state.seen | near_agent) if env.observation == "view" else jnp.ones((height, width), bool)

    vpos = state.victim_pos
    open_victim = ~state.triaged & ~state.dead & known[vpos[:, 0], vpos[:, 1]]
    critical = open_victim & (jnp.asarray(env.victim_kind) == CRITICAL)
    rubble = state.rubble & known
    solid, victim_at = env._victim_cells(state)  # blocked or holding a victim; each cell's victim (-1: none)
    passable = ~solid & ~rubble

    def cells(mask):  # bool[H, W]: the cells of the victims in ``mask``
        return (victim_at >= 0) & mask[victim_at]

    fields = jnp.stack([distance_to(cells(critical), passable), distance_to(cells(open_victim), passable),
                        distance_to(rubble, passable), distance_to(~blocked & ~known, passable)])
    # each agent's order of targets (rows of ``fields``): medics victims then search, engineers rubble then search
    order = jnp.asarray(np.where(env.roles[:, None] == ENGINEER, [2, 3, 3], [0, 1, 3]))

    front = state.agent_pos[:, None, :] + jnp.asarray(DIR_DELTA)[None]  # [agents, 4 directions, 2]
    inside = jnp.all((front >= 0) & (front < jnp.array([height, width])), -1)
    front = jnp.clip(front, 0, jnp.array([height - 1, width - 1]))
    here = state.agent_pos

    def one(i, key):
        field = fields[order[i]]  # [3, H, W]
        reach = field[:, here[i, 0], here[i, 1]] < FAR
        chosen = field[jnp.argmax(reach)]  # the first target kind with a known route (none: the last)
        value = jnp.where(inside[i], chosen[front[i, :, 0], front[i, :, 1]], FAR)
        turns = (jnp.arange(4) - state.agent_dir[i]) % 4  # 0 ahead, 1 right, 2 behind, 3 left
        best = jnp.argmin(value * 4 + jnp.asarray([0, 1, 2, 1])[turns])
        ahead = best == state.agent_dir[i]
        act_on = value[best] == 0  # the target itself is in front: triage it or clear it
        move = jnp.where(act_on, TRIAGE, FORWARD)
        turn = jnp.where(turns[best] == 3, TURN_LEFT, TURN_RIGHT)
        action = jnp.where(ahead, move, turn)
        cell = front[i, state.agent_dir[i]]
        held = jnp.any(jnp.all(here == cell, -1) & (jnp.arange(env.n_agents) != i))
        random_turn = jnp.where(jax.random.bernoulli(key), TURN_LEFT, TURN_RIGHT)
        action = jnp.where((action == FORWARD) & held, random_turn, action)
        return jnp.where(reach.any(), action, TURN_LEFT).astype(jnp.int32)

    return jax.vmap(one)(jnp.arange(env.n_agents), jax.random.split(key, env.n_agents))


def rollout(env: USAREnv, reset_key: jax.Array, key: jax.Array, trace: bool = False) -> dict:
    """One scripted team episode from the reset of ``reset_key`` (the draw), tie-breaks from ``key``:
    return, steps (the horizon if unfinished), victims saved and critical victims saved; with ``trace``, also ``states`` (the reset state and the state after each step, [horizon + 1])
    and ``rewards`` ([horizon])."""
    _, state = env.reset(reset_key)

    def step(carry, k):
        state, ret, done, steps = carry
        _, nxt, reward, end, _ = env.step(k, state, act(env, state, k))
        nxt = jax.tree.map(lambda x, y: jnp.where(done, x, y), state, nxt)
        reward = jnp.where(done, 0.0, reward)
        return (nxt, ret + reward, done | end, steps + (~done).astype(jnp.int32)), (nxt, reward) if trace else None

    init = (state, jnp.zeros((), jnp.float32), jnp.array(False), jnp.zeros((), jnp.int32))
    (last, ret, _, steps), trajectory = jax.lax.scan(step, init, jax.random.split(key, env.horizon))
    is_critical = jnp.asarray(env.victim_kind) == CRITICAL
    out = {"return": ret, "steps": steps, "saved": last.triaged.sum(), "critical_saved": (last.triaged & is_critical).sum()}
    if trace:
        states, rewards = trajectory
        out["states"] = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), state, states)
        out["rewards"] = rewards
    return out
