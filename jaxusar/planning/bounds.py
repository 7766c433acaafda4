"""Bounds on the team's optimum that stay cheap at any map size, and the per-state bounds that prune the
exact search.

Every bound here relaxes the team problem the same way: each medic alone on the map (other agents
ignored, so no collisions), rubble treated as floor (no waiting for an engineer), victims blocking as they
do. Engineers take no victims (only medics triage). Victims needing k > 1 TRIAGE actions: several medics may
share them, so a victim is charged ceil(k / m) TRIAGE actions, m = the medics that can reach it; that is
what the medic doing most of its triage does at least, and exactly k with one medic. Solo tours then come
from an exact dynamic programme over (victims triaged, the pose the last one was triaged from), and the
team's over the ways to split the victims among the medics (``_makespans``).

``team_lower_bound``: steps to triage every victim (no team does it in fewer; the optimum itself for one
medic on a map without rubble). ``episode_lower_bound``: steps of any episode (it ends when every victim is
triaged or dead, or at the horizon). ``team_return_bound``: the return no policy can beat, knowing the victims:
only victim sets the relaxed medics can triage in time (regular ones within the horizon, critical ones
before they expire) count. ``StateBounds``: per state of the joint search, the fewest steps before each
victim can be triaged (``optimal.py`` cuts states that cannot beat the answer with it).
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage

from jaxusar.envs.layout import CRITICAL, ENGINEER, MEDIC
from jaxusar.envs.usar import DIR_DELTA, USAREnv
from jaxusar.planning.distances import UNREACHABLE, _pose_index, pose_distances
from jaxusar.planning.search import States, Unreachable, _Codec

INF = np.iinfo(np.int64).max // 4  # "never": sums of two stay in range
MAX_VICTIMS = 16  # the subset programmes enumerate 2^victims sets (3^victims for the split)
MAX_RUBBLE_CONFIGS = 1 << 12  # StateBounds labels the open cells per rubble configuration


def _require_fixed(env: USAREnv, what: str) -> None:
    if env.n_drawn:
        raise ValueError(f"{what} needs fixed victims; {env.layout.name!r} draws {env.n_drawn} at reset: bound each "
                         "draw (planning.fixed_victims(env, state.victim_pos)) or use planning.clairvoyant_reference")


def _triage_poses(env: USAREnv) -> tuple[np.ndarray, np.ndarray]:
    """(poses int[Q], victim_of int[Q]): every open cell next to a victim, facing it (rubble is open)."""
    h, w = env.height, env.width
    poses, victim_of = [], []
    for k, (r, c) in enumerate(env.victim_pos):
        for d, (dr, dc) in enumerate(DIR_DELTA):
            pr, pc = r - dr, c - dc  # facing d from (pr, pc) looks at (r, c)
            if 0 <= pr < h and 0 <= pc < w and not env._solid[pr, pc]:
                poses.append(int(_pose_index(w, pr, pc, d))), victim_of.append(k)
    return np.asarray(poses, np.int64), np.asarray(victim_of, np.int64)


def _starts(env: USAREnv, agents: np.ndarray) -> np.ndarray:
    r, c = np.asarray(env.layout.agent_start)[agents].T
    return _pose_index(env.width, r, c, env.start_dir)


def _triage_tables(env: USAREnv):
    """The relaxation's single-agent tables: (poses int[Q], victim_of int[Q]) as ``_triage_poses``;
    dist int64[Q, P] (``pose_distances`` to each triage pose); to_triage int64[V, P] (steps from each pose
    until one agent alone triages victim v, its TRIAGE action included; INF where it cannot); sharing
    int64[V] (the medics that can reach victim v, at least 1); charge int64[V] (the TRIAGE actions charged
    to the medic that does most of v's triage: ceil(needed / sharing))."""
    poses, victim_of = _triage_poses(env)
    dist = pose_distances(env, poses)  # [Q, P]
    to_triage = np.full((env.n_victims, dist.shape[1]), INF, np.int64)
    for q, v in enumerate(victim_of):
        to_triage[v] = np.minimum(to_triage[v], np.where(dist[q] >= UNREACHABLE, INF, dist[q] + 1))
    medics = np.flatnonzero(env.roles == MEDIC)
    sharing = np.maximum(1, (to_triage[:, _starts(env, medics)] < INF).sum(1))
    charge = -(-np.asarray(env.needed, np.int64) // sharing)
    return poses, victim_of, dist, to_triage, sharing, charge


def _solo_tours(env: USAREnv, deadline: np.ndarray | None = None) -> np.ndarray:
    """int64[n_medics, 2^V]: per medic alone, the fewest steps to triage exactly the victims of each set
    (bit v = victim v), each charged ``_triage_tables``' TRIAGE actions; with ``deadline`` int[V], only
    orders that triage every victim by its deadline (steps from the start) count. INF where none does."""
    v = env.n_victims
    if v > MAX_VICTIMS:
        raise ValueError(f"the team bounds enumerate victim subsets: {v} victims is more than {MAX_VICTIMS}")
    poses, victim_of, dist, _, _, charge = _triage_tables(env)
    charge = charge[victim_of]  # [Q]
    medics = np.flatnonzero(env.roles == MEDIC)
    full, n_poses = 1 << v, len(poses)
    bit = 1 << victim_of  # [Q]
    moves = dist[:, poses].T  # [from q', to q]
    between = np.where(moves >= UNREACHABLE, INF, moves + charge[None, :])  # move to q, then triage
    late = np.full(n_poses, INF, np.int64) if deadline is None else np.asarray(deadline, np.int64)[victim_of]
    tours = np.zeros((len(medics), full), np.int64)
    for k, start in enumerate(_starts(env, medics)):
        f = np.full((full, n_poses), INF, np.int64)  # f[S, q]: S triaged, the last one from pose q
        first = np.where(dist[:, start] >= UNREACHABLE, INF, dist[:, start] + charge)
        f[bit, np.arange(n_poses)] = np.where(first <= late, first, INF)
        for s in range(1, full):  # subsets in increasing order: s minus one victim comes before s
            last = (s & bit) != 0
            prev = s & ~bit  # per pose q: the set before its victim
            reach = f[prev[:, None], np.arange(n_poses)[None, :]] + between.T  # [q, q']: end at q after q'
            ok = (prev[:, None] & bit[None, :]) != 0  # q' triaged a victim of the set before
            step = np.where(ok, reach, INF).min(1)
            row = np.where(last, np.minimum(f[s], step), INF)
            f[s] = np.where(row <= late, np.minimum(row, INF), INF)
        tours[k] = f.min(1)
        tours[k, 0] = 0
    return tours


def _makespans(env: USAREnv, deadline: np.ndarray | None = None) -> np.ndarray:
    """int64[2^V]: over every split of each victim set among the medics, the least makespan (the longest
    medic's solo tour, ``_solo_tours``); INF where no split does it (in time, with ``deadline``)."""
    tours = _solo_tours(env, deadline)
    full = tours.shape[1]
    best = tours[0].copy()
    for i in range(1, len(tours)):  # best[S] = min over T subset of S of max(best[S \ T], tours[i][T])
        new = np.full(full, INF, np.int64)
        for s in range(full):
            t = s
            while True:
                new[s] = min(new[s], max(best[s & ~t], tours[i][t]))
                if t == 0:
                    break
                t = (t - 1) & s
        best = new
    return best


def team_lower_bound(env: USAREnv) -> int:
    """A lower bound on ``optimal_team_steps`` (every victim triaged) that stays cheap at any map size (its
    cost grows with the victims instead: 2^victims pose tables per medic, 3^victims for the split; at
    most 16 victims).

    Over every split of the victims among the medics, the least makespan (the longest medic's tour) of
    single-agent exact tours: each medic alone on the map (victims block, other agents ignored, rubble is
    floor) triages its victims in the best order, turns and TRIAGE actions counted (a victim needing k
    TRIAGE actions is charged ceil(k / m), m = the medics that can reach it: they may share it). Engineers
    take no victims. Exact by dynamic programming: per medic over (victims triaged, the pose it triaged the
    last one from), then over victim subsets for the split. Collisions, rubble and shared triage are left
    out, so the bound is <= the exact optimum (tested on every map where the joint search runs) and equal
    to it for one medic on a map without rubble. It ignores expiry: where critical victims expire, the
    optimum it bounds (saving everyone) may not exist.
    """
    _require_fixed(env, "team_lower_bound")
    best = _makespans(env)[-1]
    if best >= INF:
        raise Unreachable(f"some victim of {env.layout.name!r} cannot be triaged")
    return int(best)


def _masks(env: USAREnv) -> tuple[int, int]:
    bits = 1 << np.arange(env.n_victims)
    critical = env.victim_kind == CRITICAL
    return int(bits[~critical].sum()), int(bits[critical].sum())


def _episode_lengths(env: USAREnv, makespans: np.ndarray) -> np.ndarray:
    """int64[2^V]: a lower bound on the length of an episode that ends with exactly the set S triaged: the
    horizon if a victim that never dies is left (a regular one, or any where none expire), else S's
    makespan, and no less than ``critical_expires`` if a critical victim is left (it dies then); at most
    the horizon."""
    regular, critical = _masks(env)
    sets = np.arange(len(makespans))
    length = makespans.copy()
    if env.expires:
        length = np.where((sets & critical) != critical, np.maximum(length, env.critical_expires), length)
    lasting = regular if env.expires else regular | critical
    length = np.where((sets & lasting) != lasting, env.horizon, length)
    return np.minimum(length, env.horizon)


def episode_lower_bound(env: USAREnv) -> int:
    """A lower bound on the length of every episode (DESIGN.md contract part 2: it ends when every victim is
    triaged or dead, or at the horizon), over every set of victims it may triage (``_makespans``). Where
    victims expire, this is what the best-return episode's steps are measured against; elsewhere it is
    ``team_lower_bound`` (capped at the horizon)."""
    _require_fixed(env, "episode_lower_bound")
    return int(_episode_lengths(env, _makespans(env)).min())


def _worth(env: USAREnv) -> np.ndarray:
    """float64[V]: the reward for triaging each victim."""
    return np.where(env.victim_kind == CRITICAL, env.critical_reward, env.triage_reward).astype(np.float64)


def _deadlines(env: USAREnv) -> np.ndarray:
    """int64[V]: the last step at which each victim's triage may complete: critical_expires for critical
    victims where they expire (the TRIAGE action taken at t = critical_expires - 1 still saves it), else
    the horizon."""
    critical = (env.victim_kind == CRITICAL) & env.expires
    return np.where(critical, env.critical_expires or 0, env.horizon).astype(np.int64)


def team_return_bound(env: USAREnv) -> float:
    """An upper bound on the undiscounted return of any episode on ``env`` (fixed victims: any policy, even
    one that knows where the victims are).

    The best over the victim sets the relaxed medics (``_makespans``: alone, rubble as floor, shared
    triage) can triage in time, every regular one within the horizon and every critical one before it
    expires: the rewards of the set, plus step_penalty times a lower bound on the episode's length with
    that set triaged (``_episode_lengths``; the horizon if step_penalty > 0). Any real episode triages a set
    the relaxation also reaches in time, so no policy can beat it.
    """
    _require_fixed(env, "team_return_bound")
    deadline = _deadlines(env)
    makespans = _makespans(env, deadline)
    sets = np.arange(len(makespans))
    rewards = ((sets[:, None] >> np.arange(env.n_victims)) & 1) @ _worth(env)
    length = _episode_lengths(env, makespans) if env.step_penalty <= 0 else np.full(len(sets), env.horizon)
    value = np.where(makespans < INF, rewards + env.step_penalty * length, -np.inf)
    return float(value.max())


class StateBounds:
    """Per state of the joint search (``search.States`` at time t), the fewest further steps before each
    victim can be triaged (``victim_steps``), none of them overestimated, so cutting the states that cannot
    beat an answer keeps the search exact.

    A victim's steps are the closest medic's solo steps to triage it (``_triage_tables``: victims block,
    rubble is floor, other agents ignored) plus its remaining TRIAGE actions (shared among the medics that
    can reach it). On maps with engineers, a victim that no medic can reach past the rubble still there
    must also wait for some engineer to clear a rubble cell first (its solo steps to do so, plus the
    victim's remaining TRIAGE actions). 0 once triaged; INF when dead or out of every medic's reach.
    """

    def __init__(self, env: USAREnv):
        _require_fixed(env, "StateBounds")
        self.env = env
        self.medics = np.flatnonzero(env.roles == MEDIC)
        self.engineers = np.flatnonzero(env.roles == ENGINEER)
        _, _, _, self.to_triage, self.sharing, _ = _triage_tables(env)
        self.needed = _Codec(env).needed
        self.critical = env.victim_kind == CRITICAL
        cells = _Codec(env).rubble_cells
        self.gated = len(self.engineers) > 0 and 0 < len(cells) and (1 << len(cells)) <= MAX_RUBBLE_CONFIGS
        if self.gated:
            self._rubble_tables(env, cells)

    def _rubble_tables(self, env: USAREnv, cells: np.ndarray) -> None:
        h, w = env.height, env.width
        solid = env._solid
        self.to_clear = np.full((len(cells), h * w * 4), INF, np.int64)  # solo steps to clear rubble cell k
        for k, (r, c) in enumerate(cells):
            faces = [int(_pose_index(w, r - dr, c - dc, d)) for d, (dr, dc) in enumerate(DIR_DELTA)
                     if 0 <= r - dr < h and 0 <= c - dc < w and not solid[r - dr, c - dc]]
            if faces:
                dist = pose_distances(env, np.asarray(faces)).min(0)
                self.to_clear[k] = np.where(dist >= UNREACHABLE, INF, dist + 1)
        # per rubble configuration (bit k: cell k still there), the open cells' 4-connected components and,
        # per component, the victims a medic standing in it can face
        configs = 1 << len(cells)
        self.component = np.zeros((configs, h * w), np.int64)
        labels = []
        for config in range(configs):
            free = ~solid
            there = (config >> np.arange(len(cells))) & 1 == 1
            free[tuple(cells[there].T)] = False
            label, _ = scipy.ndimage.label(free)
            self.component[config] = label.ravel()
            labels.append(label)
        self.faces = np.zeros((configs, int(self.component.max()) + 1, self.env.n_victims), bool)
        for config, label in enumerate(labels):
            for v, (r, c) in enumerate(env.victim_pos):
                for dr, dc in DIR_DELTA:
                    if 0 <= r + dr < h and 0 <= c + dc < w and label[r + dr, c + dc] > 0:
                        self.faces[config, label[r + dr, c + dc], v] = True

    def victim_steps(self, t: int, s: States) -> np.ndarray:
        """int64[N, V]: the fewest further steps before each victim can be triaged (see the class doc)."""
        env = self.env
        pose = _pose_index(env.width, s.pos[..., 0], s.pos[..., 1], s.dirs)  # [N, n_agents]
        arrive = self.to_triage[:, pose[:, self.medics]].min(-1).T  # [N, V]
        rest = -(-(self.needed - s.progress) // self.sharing)  # TRIAGE actions still needed, shared
        steps = np.minimum(arrive + np.maximum(rest - 1, 0), INF)
        if self.gated:
            config = (s.rubble.astype(np.int64) << np.arange(s.rubble.shape[1])).sum(1)
            cell = s.pos[:, self.medics, 0] * env.width + s.pos[:, self.medics, 1]
            reachable = self.faces[config[:, None], self.component[config[:, None], cell]].any(1)  # [N, V]
            clear = np.where(s.rubble, self.to_clear[:, pose[:, self.engineers]].min(-1).T, INF).min(1)  # [N]
            steps = np.where(reachable, steps, np.maximum(steps, np.minimum(clear[:, None] + rest, INF)))
        steps = np.where(s.triaged, 0, steps)
        if env.expires and t >= env.critical_expires:
            steps = np.where(self.critical & ~s.triaged, INF, steps)
        return steps

    def steps_to_go(self, t: int, s: States) -> np.ndarray:
        """int64[N]: the fewest further steps before every victim is triaged (INF: never)."""
        steps = self.victim_steps(t, s)
        return steps.max(1) if steps.shape[1] else np.zeros(len(steps), np.int64)
