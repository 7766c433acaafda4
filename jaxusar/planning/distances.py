"""Single-agent distance tables: one agent alone on the map (other agents removed, victims block, rubble is
floor), from every pose at once. The sub-policies' optimum (``steps_to_goal``) and the building block of the
team bounds (``pose_distances``). Successors are the env's own rules (``apply_actions``).

A pose is (row, col, dir), flattened as ``(row * W + col) * 4 + dir`` (``_pose_index``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxusar.envs.usar import DIR_DELTA, N_ACTIONS, TRIAGE


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


def steps_to_clear(solid: np.ndarray, rubble_cells: np.ndarray, bits: int) -> np.ndarray:
    """int32[M, H, W, 4]: fewest steps for one engineer alone to clear the rubble cells of mask ``bits``
    from every (mode, row, col, dir); -1 = never (or a cell solid in that mode), 0 where they are cleared.

    A mode is the bitmask of ``rubble_cells`` int[K, 2] cleared (M = 2^K); a cell not cleared is solid,
    and TRIAGE facing it clears it (the contract's engineer tool). Exact: the fixed point of
    dist = min_a 1 + dist[next] over all modes at once, the clearing actions crossing modes."""
    h, w = solid.shape
    n_cells = len(rubble_cells)
    n_modes, poses = 2 ** n_cells, h * w * 4
    no_victim = jnp.full((h, w), -1, jnp.int32)
    index = np.full((h, w), -1, np.int64)
    index[tuple(np.asarray(rubble_cells).T)] = np.arange(n_cells)
    rows, cols, dirs = np.meshgrid(np.arange(h), np.arange(w), np.arange(4), indexing="ij")
    fr, fc = rows + DIR_DELTA[dirs, 0], cols + DIR_DELTA[dirs, 1]
    inside = (fr >= 0) & (fr < h) & (fc >= 0) & (fc < w)
    front = np.where(inside, index[np.clip(fr, 0, h - 1), np.clip(fc, 0, w - 1)], -1).reshape(-1)
    succ, covered = [], []
    for m in range(n_modes):
        rubble = (index >= 0) & ~((m >> np.maximum(index, 0)) & 1).astype(bool)
        nxt = np.asarray(_single_agent_successors(jnp.asarray(solid | rubble), no_victim)[0])
        s = m * poses + _pose_index(w, nxt[..., 0], nxt[..., 1], nxt[..., 2]).reshape(poses, N_ACTIONS)
        k = np.maximum(front, 0)
        clears = (front >= 0) & ~((m >> k) & 1).astype(bool)
        s[clears, TRIAGE] = (m | (1 << k[clears])) * poses + np.arange(poses)[clears]
        succ.append(s)
        covered.append(np.repeat((solid | rubble).reshape(-1), 4))
    succ, covered = np.concatenate(succ), np.concatenate(covered)
    inf = np.iinfo(np.int32).max // 2
    done = np.repeat((np.arange(n_modes) & bits) == bits, poses)
    dist = np.where(done, 0, inf).astype(np.int64)
    dist = _fixed_point(dist, lambda d: 1 + d[succ].min(-1))
    dist[covered] = -1
    return np.where(dist >= inf, -1, dist).astype(np.int32).reshape(n_modes, h, w, 4)
