"""Single-agent distance tables: one agent alone on the map (other agents removed, victims block, rubble is
floor), from every pose at once. The sub-policies' optimum (``steps_to_goal``) and the building block of the
team bounds (``pose_distances``). Successors are the env's own rules (``apply_actions``).

A pose is (row, col, dir), flattened as ``(row * W + col) * 4 + dir`` (``_pose_index``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxusar.envs.usar import N_ACTIONS


def _fixed_point(dist: np.ndarray, relax) -> np.ndarray:
    """Iterate dist = min(dist, relax(dist)) until nothing changes (shortest paths, Bellman-Ford style)."""
    while True:
        new = np.minimum(dist, relax(dist))
        if np.array_equal(new, dist):
            return dist
        dist = new


@jax.jit
def _single_agent_successors(solid, victim_at):
    """int32[H, W, 4, A, 3] next (row, col, dir) and bool[H, W, 4, A] 'triaged the victim' per action."""
    from jaxusar.envs.usar import apply_actions

    h, w = solid.shape
    rows, cols, dirs, acts = jnp.meshgrid(jnp.arange(h), jnp.arange(w), jnp.arange(4), jnp.arange(N_ACTIONS),
                                          indexing="ij")

    def one(r, c, d, a):
        pos, dr, _, newly = apply_actions(solid, victim_at, jnp.array([[r, c]]), jnp.array([d]),
                                          jnp.zeros((1,), bool), jnp.array([a]))
        return jnp.array([pos[0, 0], pos[0, 1], dr[0]]), newly[0]

    return jax.vmap(jax.vmap(jax.vmap(jax.vmap(one))))(rows, cols, dirs, acts)


def steps_to_goal(solid: np.ndarray, victim_at: np.ndarray, goal_region_mask: np.ndarray | None = None,
                  triage: bool = False) -> np.ndarray:
    """int32[H, W, 4]: fewest steps from every (row, col, dir) for one agent alone to reach its goal.

    Goal: stand in a cell of ``goal_region_mask`` bool[H, W] (0 steps if already there), or, with
    ``triage``, triage the victim marked in ``victim_at`` (its TRIAGE action counts). -1 = unreachable.
    Exact (a fixed point of dist = min_a 1 + dist[next]); the successors are the env's own rules.
    """
    nxt, hit = (np.asarray(x) for x in _single_agent_successors(jnp.asarray(solid), jnp.asarray(victim_at)))
    h, w = solid.shape
    inf = np.iinfo(np.int32).max // 2
    dist = np.full((h, w, 4), inf, np.int64)
    if goal_region_mask is not None:
        dist[goal_region_mask] = 0

    def relax(dist):
        after = dist[nxt[..., 0], nxt[..., 1], nxt[..., 2]]  # [H, W, 4, A]
        return (np.where(hit, 1, 1 + after) if triage else 1 + after).min(-1)

    dist = _fixed_point(dist, relax)
    dist[solid] = -1
    return np.where(dist >= inf, -1, dist).astype(np.int32)


def _pose_index(width: int, r, c, d):
    return (np.asarray(r) * width + np.asarray(c)) * 4 + np.asarray(d)


# what pose_distances puts where a pose cannot reach its target (sums of a few stay far from overflow)
UNREACHABLE = np.iinfo(np.int32).max // 4


def pose_distances(env, targets: np.ndarray) -> np.ndarray:
    """int64[T, H*W*4]: fewest moves (FORWARD and turns) for one agent alone to stand in pose ``targets[t]``
    (flat (row * W + col) * 4 + dir) from every pose; ``UNREACHABLE`` where it cannot (victims block,
    rubble is floor). ``env`` needs fixed victims (its ``_solid``/``_victim_at``)."""
    nxt = np.asarray(_single_agent_successors(jnp.asarray(env._solid), jnp.asarray(env._victim_at))[0])
    succ = _pose_index(env.width, nxt[..., 0], nxt[..., 1], nxt[..., 2]).reshape(-1, N_ACTIONS)
    dist = np.full((len(targets), succ.shape[0]), UNREACHABLE, np.int64)
    dist[np.arange(len(targets)), targets] = 0
    return _fixed_point(dist, lambda d: 1 + d[:, succ].min(-1))
