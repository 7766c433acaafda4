"""Option sub-policies trained on pseudo-rewards (paper Sec. IV-B, Fig. 4).

Each task is one option for one agent, in the map with the other agents and the other victims
removed: +100 on reaching the sub-goal region (NAVIGATE) or on triaging the victim (TRIAGE), -1 every
step, terminal there. Tasks:

* ``hierarchical.navigation: chained`` (the default; the paper's "chaining options", its future work,
  Sec. VI): NAVIGATE-TO-X for every region X that is a hop of some shortest region path to a room,
  one task shared by all medics, trained and tested from anywhere in its initiation set (the regions
  adjacent to X). The coordinator's NAVIGATE-TO-R then starts in any region and runs, region by
  region, the task of the next hop (``policy_table``): at most one task per region, whatever the
  number of medics (never medics x rooms^2).
* ``goal`` (the issue's other route, measured against ``chained`` in benchmarks/README.md): one
  goal-conditioned NAVIGATE task for every room, shared by all medics and rooms: its input also holds a
  one-hot of the goal room, its episodes start anywhere outside the goal room with a goal drawn with
  the start, and the coordinator's NAVIGATE-TO-R runs it with R as the goal, from any region.
* ``adjacent`` (the paper, two_rooms' settings): NAVIGATE-TO-R for agent i (the paper trains "each medic
  to each room"), where i's start region is adjacent to R. Half of the training episodes start from
  agent i's start, half anywhere in the option's initiation set (every open cell of the regions adjacent
  to R, any facing); greedy tests start from agent i's start, which is what Fig. 4 measures.
  (Initiation-set starts alone: the exact path from the start was rarely practised; measured 7 of 8
  trials short of optimal on one task.) Why not train from the start alone: the coordinator terminates
  every option when one completes, so navigation is often re-issued mid-way from hall states a
  start-only policy never saw; such a policy then loops to the horizon (measured: no coordinator trial
  ever triaged both).
* TRIAGE-v, shared by all agents (its input is one agent's features), starting uniformly at any open
  cell of v's room with any facing (``triage_start: room``: "assuming the agent is already in the
  room", Sec. IV-B) or at the room's entry cells (``entry``: cells next to another region).

Wherever a task's episodes start, ``hierarchical.focus_starts`` of them (0.5 by default) start instead
at an initiation state from which the latest test's greedy policy was not optimal, while there is one
(``SubtaskEnv.refocus``): the few hall cells a policy still gets wrong are otherwise a start once in
hundreds of episodes (measured: benchmarks/README.md, "Starts where the last test failed").

Rubble (contract part 2): CLEAR-g, an engineer's task, starts anywhere in the regions that hold or
touch group g and ends when every cell of g is cleared (+100). Every task on a map with rubble runs in
each *mode* (the bitmask of rubble cells cleared; ``options.Rubble``), rubble not yet cleared solid, and
its states are those from which its goal can be reached in their mode: the coordinator may start any
option between two clearings, so the sub-policies are trained and judged exact over all of them. A NAVIGATE
cut off from its room by rubble (in a mode) instead ends, in training, with a no-op (TRIAGE) at a cell
beside the rubble in its way (``options.waiting_cells``): its greedy policy then waits there, in the
team env, until a clearing changes its mode and it goes on into the room.

Victims drawn at reset (``options.method_env``): TRIAGE-IN-R is one goal-conditioned task per room,
its goals the room's slots (``Task.targets``; the cells where a victim may lie, obstacles in every
task), trained and judged from every cell of the room with every goal; the coordinator's macro env tells
it the slot it works on.

Every task has the same observation shape: one agent's one-hot row, col and dir, plus one flag
(the task's victim triaged; 0 for NAVIGATE), on a map with rubble a flag per rubble cell (cleared), and
with ``goal`` navigation a one-hot of the goal
(the first for every other task), so all tasks x all trials stack into one vmapped batch; the per-task
map data (cells blocked, the task's victim, its goals, start states, discount, the exact distance to
each goal from every state) travel as env params. A task's states are (row, col, facing, index), the index being goal index x modes + mode;
every task but the goal-conditioned one has a single goal, index 0, and a map without rubble one mode. The discount is per task (paper Fig. 4f: the
triage-bottom task needed gamma 0.9), stored in each replay row.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxusar import planning
from jaxusar.algos.options import CLEAR, NAVIGATE, Options, Rubble, next_hop, room_label, waiting_cells
from jaxusar.config import ConfigError, DQNConfig
from jaxusar.core.learners import IndependentDQN, default_row, dqn_target
from jaxusar.envs.usar import DIR_DELTA, N_ACTIONS, TRIAGE, EnvState, USAREnv, apply_actions

SUCCESS_REWARD, STEP_REWARD = 100.0, -1.0


@dataclasses.dataclass(frozen=True)
class Task:
    name: str
    option: int           # the coordinator's option it executes; -1: a hop of chained navigation, or goal navigation
    agent: int            # the agent whose start is used (NAVIGATE); -1 = any agent (TRIAGE)
    starts: np.ndarray    # int32[M, 4] (row, col, dir, goal index) training start states
    test_starts: np.ndarray  # int32[N, 4] greedy-test start states (the paper's single-start test)
    initiation: np.ndarray   # int32[K, 4] every state the coordinator may start or re-issue the option in
    region: int           # the region to reach (NAVIGATE), -1 for TRIAGE and goal-conditioned navigation
    victim: int           # the victim to triage (TRIAGE), -1 for NAVIGATE
    goals: tuple[int, ...] = ()  # goal-conditioned navigation: the region of each goal index
    clears: int = 0       # CLEAR: the mode bits of its rubble group (done when all are cleared); 0 otherwise
    targets: tuple[int, ...] = ()  # goal-conditioned TRIAGE (drawn victims): the slot of each goal index
    every_mode: bool = True  # False: its states are mode 0's only (no mode's rubble changes its way)
    arrays: tuple | None = dataclasses.field(default=None, compare=False, repr=False)  # ``_task_arrays``, once

    @property
    def goal_regions(self) -> tuple[int, ...]:
        """The region to reach for each goal index (-1: none, a TRIAGE task)."""
        return self.goals or (-1,) * len(self.targets) or (self.region,)


@struct.dataclass
class TaskParams:
    """Per-task env data (a leading task axis when stacked)."""

    solid: jax.Array        # bool[H, W]
    victim_at: jax.Array    # int32[G, H, W]: 0 on the task's victim (goal-conditioned TRIAGE: goal g's slot), -1 elsewhere
    goal_region: jax.Array  # int32[G]: the region to reach for each goal index, -1 for a triage task
    starts: jax.Array       # int32[M, 4] (row, col, dir, goal index), padded by repetition
    n_starts: jax.Array     # int32
    test_starts: jax.Array  # int32[N, 4], padded by repetition
    n_test_starts: jax.Array
    initiation: jax.Array   # int32[K, 4], padded by repetition
    n_initiation: jax.Array
    dist: jax.Array         # int32[G, H, W, 4]: optimal steps from each state to each goal's sub-goal
    gamma: jax.Array        # float32
    clears: jax.Array       # int32: the mode bits a CLEAR task clears (0: not a CLEAR task)
    wait: jax.Array         # bool[G * modes, H, W]: where a NAVIGATE cut off by rubble ends with a no-op
    weak: jax.Array         # bool[K]: the initiation states the latest test's greedy policy was not optimal
                            # from (``SubtaskEnv.refocus``); False on padding


@struct.dataclass
class SubtaskState:
    """One agent's team env state in a sub-task, and the goal index it is after."""

    env: EnvState
    goal: jax.Array  # int32

    agent_pos = property(lambda self: self.env.agent_pos)
    agent_dir = property(lambda self: self.env.agent_dir)
    triaged = property(lambda self: self.env.triaged)
    t = property(lambda self: self.env.t)


def _entry_cells(region: np.ndarray, r: int) -> list[tuple[int, int]]:
    cells = []
    for (i, j) in np.argwhere(region == r):
        for di, dj in DIR_DELTA:
            ni, nj = i + di, j + dj
            if 0 <= ni < region.shape[0] and 0 <= nj < region.shape[1] and region[ni, nj] not in (-1, r):
                cells.append((int(i), int(j)))
                break
    return cells


def _states(env: USAREnv, regions: np.ndarray, goal: int = 0) -> np.ndarray:
    """int32[K, 4]: every open cell of the regions where ``regions`` bool[R] holds (victims' cells aside),
    any facing, with goal index ``goal``."""
    region = env.graph.cell_region
    victims = {tuple(v) for v in env.layout.victim_pos}
    cells = np.argwhere(regions[np.maximum(region, 0)] & (region >= 0))
    return np.array([[r, c, d, goal] for r, c in cells if (r, c) not in victims for d in range(4)],
                    np.int32).reshape(-1, 4)


def _in_modes(rubble: Rubble, states: np.ndarray, clears: int = 0) -> np.ndarray:
    """``states`` in every mode of ``rubble`` (column 3: goal index x modes + mode), without the cells a
    mode's rubble covers; ``clears``: only the modes where those bits are not all set. No rubble: as given."""
    if not rubble.n_cells:
        return states
    rows = []
    for m in range(rubble.n_modes):
        if clears and (m & clears) == clears:
            continue
        kept = states[~np.asarray(rubble.uncleared(m))[states[:, 0], states[:, 1]]].copy()
        kept[:, 3] = kept[:, 3] * rubble.n_modes + m
        rows.append(kept)
    return np.concatenate(rows)


def _navigation_task(env: USAREnv, name: str, goal: int, option: int, agent: int, navigate_start: str) -> Task:
    """NAVIGATE to region ``goal`` from every open cell of the regions adjacent to it (victims' cells
    aside), any facing; ``agent`` >= 0: training and tests use that medic's start (see the module doc)."""
    layout, rubble = env.layout, Rubble.of(env.layout)
    initiation = _in_modes(rubble, _states(env, env.graph.adjacency[:, goal]))
    if agent < 0:
        return Task(name, option, agent, initiation, initiation, initiation, goal, -1)
    start = _in_modes(rubble, np.array([[*layout.agent_start[agent], env.start_dir, 0]], np.int32))
    starts = initiation if navigate_start == "initiation" else \
        np.concatenate([np.resize(start, (len(initiation), 4)), initiation])  # 1:1 mixture
    return Task(name, option, agent, starts, start, initiation, goal, -1)


def make_tasks(env: USAREnv, options: Options, triage_start: str = "room", navigate_start: str = "mixed",
               navigation: str = "adjacent") -> list[Task]:
    """The sub-tasks of ``options`` on ``env``. ``navigate_start``: where NAVIGATE training episodes
    start: ``mixed`` (half at the medic's start, half anywhere in the initiation set) or ``initiation``
    (uniformly over the initiation set, which holds the medic's start).

    ``navigation``: ``adjacent`` (the paper): a task per medic and room adjacent to the medic's start
    region; ``chained``: one task per region that is a hop of some shortest region path to a room
    (``options.next_hop``), shared by all medics, trained and tested from anywhere in its initiation
    set; a NAVIGATE option chains them (``policy_table``). Their number is at most the regions'."""
    layout, graph, rubble = env.layout, env.graph, Rubble.of(env.layout)
    tasks = []
    if navigation == "goal":
        goals = tuple(int(options.region[o]) for o in np.flatnonzero(options.kind == NAVIGATE))
        initiation = _in_modes(rubble, np.concatenate([_states(env, options.starts_from[:, r], g)
                                                        for g, r in enumerate(goals)]))
        if len(initiation):  # else a one-region map: nowhere to navigate from
            tasks.append(Task("NAVIGATE-TO-ANY-ROOM", -1, -1, initiation, initiation, initiation, -1, -1, goals))
    if navigation == "chained":
        hop = next_hop(graph.adjacency)
        goals = sorted({int(hop[q, r]) for r in graph.rooms for q in range(graph.n_regions) if hop[q, r] >= 0})
        for g in goals:
            o = next((o for o in range(options.n) if options.kind[o] == NAVIGATE and options.region[o] == g), -1)
            name = options.names[o] if o >= 0 else f"NAVIGATE-TO-{room_label(graph.names[g])}"
            tasks.append(_navigation_task(env, name, g, o, -1, navigate_start))
    for o in range(options.n):
        if options.kind[o] == CLEAR:
            g = int(options.group[o])
            clears = int(rubble.group_bits[g])
            initiation = _in_modes(rubble, _states(env, options.open_from[:, :, o].any(0)), clears)
            tasks.append(Task(options.names[o], o, -1, initiation, initiation, initiation, -1, -1, clears=clears))
        elif options.kind[o] == NAVIGATE:
            if navigation != "adjacent":
                continue
            for i, (r, c) in enumerate(layout.agent_start):
                if graph.adjacency[graph.cell_region[r, c], options.region[o]]:
                    tasks.append(_navigation_task(env, f"agent{i}:{options.names[o]}", int(options.region[o]), o, i,
                                                  navigate_start))
        else:  # TRIAGE-v; where victims are drawn TRIAGE-IN-R, told which of its room's slots (its goal)
            room = options.region[o]
            drawn = options.slot_flag is not None
            slots = np.flatnonzero(options.slot_flag == options.victim[o]).tolist() if drawn else [int(options.victim[o])]
            cells = {tuple(layout.victim_pos[v]) for v in slots}
            in_room = [tuple(x) for x in np.argwhere((graph.cell_region == room) & ~layout.blocked)
                       if tuple(x) not in cells]  # blocked: where victims are drawn (``options.method_env``)
            from_ = in_room if triage_start == "room" else \
                [c for c in _entry_cells(graph.cell_region, room) if c not in cells]
            goals = range(len(slots))
            states = lambda where: _in_modes(rubble, np.array([[r, c, d, g] for g in goals for r, c in where
                                                               for d in range(4)], np.int32))
            starts, initiation = states(from_), states(in_room)
            tasks.append(Task(options.names[o], o, -1, starts, starts, initiation, -1, -1 if drawn else slots[0],
                              targets=tuple(slots) if drawn else ()))
    tasks = [dataclasses.replace(t, arrays=_task_arrays(env, t)) for t in tasks]  # planned once, kept
    if rubble.n_cells:  # a mode's rubble may cut a state off its goal: such states are no task's
        tasks = [_reachable(t, t.arrays[3]) for t in tasks]
        tasks = [_in_mode_zero(t, t.arrays[3], rubble.n_modes) if t.targets else t for t in tasks]
    return tasks


def _in_mode_zero(t: Task, dist: np.ndarray, modes: int) -> Task:
    """``t`` trained and judged in mode 0 only (``every_mode=False``) where no mode's rubble changes the
    fewest steps (``dist``, ``_task_arrays``) from any of its states: a room's TRIAGE behind its doorway
    (its sub-policy is then run in mode 0 whatever the rubble; 1/modes of the states to learn)."""
    s = t.initiation
    base = (s[:, 3] // modes) * modes
    if not np.array_equal(dist[s[:, 3], s[:, 0], s[:, 1], s[:, 2]], dist[base, s[:, 0], s[:, 1], s[:, 2]]):
        return t
    zero = lambda a: a[a[:, 3] % modes == 0]
    if len(zero(s)) * modes != len(s):  # some state exists in some modes only
        return t
    return dataclasses.replace(t, starts=zero(t.starts), test_starts=zero(t.test_starts), initiation=zero(s),
                               every_mode=False)


def _reachable(t: Task, dist: np.ndarray) -> Task:
    """``t`` without the states from which its goal cannot be reached (in their mode; ``dist``:
    ``_task_arrays``)."""
    keep = lambda a: a[dist[a[:, 3], a[:, 0], a[:, 1], a[:, 2]] >= 0]
    return dataclasses.replace(t, starts=keep(t.starts), test_starts=keep(t.test_starts),
                               initiation=keep(t.initiation))


def _task_arrays(env: USAREnv, t: Task):
    """(solid, victim_at, goal regions, dist) of task ``t``: dist int32[goals x modes, H, W, 4], the fewest
    steps from each state to the task's end (-1: never), by the planner in each mode."""
    layout, region, rubble = env.layout, env.graph.cell_region, Rubble.of(env.layout)
    goals = np.asarray(t.goal_regions, np.int32)
    victim_at = np.full((len(goals),) + layout.shape, -1, np.int32)
    solid = layout.blocked.copy()
    for g, v in enumerate(t.targets or ([t.victim] if t.victim >= 0 else [])):
        cell = tuple(layout.victim_pos[v])
        victim_at[(g,) + cell], solid[cell] = 0, True
    wait = np.zeros((len(goals) * rubble.n_modes,) + layout.shape, bool)
    if t.clears:
        return solid, victim_at, goals, planning.steps_to_clear(solid, rubble.cells, t.clears), wait
    dist = []
    for gi, g in enumerate(goals):
        for m in range(rubble.n_modes):
            now = solid | np.asarray(rubble.uncleared(m))
            d = planning.steps_to_goal(now, victim_at[gi], goal_region_mask=(region == g) if g >= 0 else None,
                                       triage=g < 0)
            if g >= 0 and rubble.n_cells:  # cut off by rubble: to where it waits, then one no-op (TRIAGE) there
                w = waiting_cells(solid, np.asarray(rubble.uncleared(m)), region == g)
                wait[len(dist)] = w
                to_wait = planning.steps_to_goal(now, victim_at[gi], goal_region_mask=w)
                d = np.where(d >= 0, d, np.where(to_wait >= 0, to_wait + 1, -1))
            dist.append(d)
    return solid, victim_at, goals, np.stack(dist), wait


def policy_table(env: USAREnv, options: Options, tasks: list[Task], navigation: str = "adjacent") -> np.ndarray:
    """int32[n_agents, R, O]: the task whose sub-policy agent i runs for option o while in region q (-1:
    none). ``adjacent``: the agent's own task, wherever it is; ``chained``: NAVIGATE-TO-r runs the task
    of the next region on the shortest region path from q to r; ``goal``: the goal-conditioned task in
    every region (``option_goals`` says which goal it is after; the options' initiation sets say where
    they may start), so the table is the same in every region, like the paper's."""
    table = np.full((env.n_agents, env.graph.n_regions, options.n), -1, np.int32)
    goal_task = next((k for k, t in enumerate(tasks) if t.goals), None)
    if navigation == "goal" and goal_task is not None:
        table[:, :, options.kind == NAVIGATE] = goal_task
    if navigation == "chained":
        hop = next_hop(env.graph.adjacency)
        task_to = {t.region: k for k, t in enumerate(tasks) if t.victim < 0}
        for o in np.flatnonzero(options.kind == NAVIGATE):
            for q in range(env.graph.n_regions):
                if hop[q, options.region[o]] >= 0:
                    table[:, q, o] = task_to[int(hop[q, options.region[o]])]
    for k, t in enumerate(tasks):
        if t.option >= 0 and (t.victim >= 0 or t.targets or t.clears or navigation == "adjacent"):
            table[[t.agent] if t.agent >= 0 else slice(None), :, t.option] = k
    role = options.role  # TRIAGE for medics, CLEAR for engineers
    wrong = (role >= 0)[None] & (role[None] != env.roles[:, None])  # [n_agents, O]
    table[np.broadcast_to(wrong[:, None], table.shape)] = -1
    return table


def option_goals(options: Options, tasks: list[Task]) -> np.ndarray:
    """int32[O]: the goal index a sub-policy runs each option with: NAVIGATE-TO-r's room's index in the
    goal-conditioned task's goals, 0 for every other option (and every option without such a task)."""
    goals = next((t.goals for t in tasks if t.goals), ())
    return np.array([goals.index(int(r)) if k == NAVIGATE and goals else 0
                     for k, r in zip(options.kind, options.region)], np.int32)


def task_params(env: USAREnv, tasks: list[Task], dqn_gamma: float,
               task_gamma: dict[str, float]) -> TaskParams:
    """Stacked TaskParams for ``tasks`` (numpy, leading task axis)."""
    unknown = sorted(set(task_gamma) - {t.name for t in tasks})
    if unknown:
        raise ConfigError(f"hierarchical.task_gamma names task(s) {unknown} that map {env.layout.name!r} does not have "
                          f"(its tasks: {', '.join(t.name for t in tasks)}); name one of those, or drop them with "
                          "--set 'hierarchical.task_gamma={}'")
    pad = lambda a, n: np.concatenate([a, np.repeat(a[:1], n - len(a), 0)])
    width = {k: max(len(getattr(t, k)) for t in tasks) for k in ("starts", "test_starts", "initiation")}
    n_goals = max(len(t.goal_regions) for t in tasks)
    n_modes = Rubble.of(env.layout).n_modes
    rows = []
    for t in tasks:
        if not len(t.initiation):
            raise ConfigError(f"task {t.name}: no state of its initiation set can reach its sub-goal")
        solid, victim_at, goals, dist, wait = t.arrays or _task_arrays(env, t)
        goals, dist, wait = pad(goals, n_goals), pad(dist, n_goals * n_modes), pad(wait, n_goals * n_modes)
        victim_at = pad(victim_at, n_goals)
        for k in ("test_starts", "initiation"):
            states = getattr(t, k)
            if np.any(dist[states[:, 3], states[:, 0], states[:, 1], states[:, 2]] < 0):
                raise ConfigError(f"task {t.name}: its sub-goal cannot be reached from some state of its "
                                  f"{'test starts' if k == 'test_starts' else 'initiation set'}")
        rows.append(dict(solid=solid, victim_at=victim_at, goal_region=goals,
                         **{k: pad(getattr(t, k), width[k]) for k in width},
                         **{"n_" + k: np.int32(len(getattr(t, k))) for k in width},
                         dist=dist, gamma=np.float32(task_gamma.get(t.name, dqn_gamma)), clears=np.int32(t.clears),
                         wait=wait,
                         weak=np.zeros(width["initiation"], bool)))
    return TaskParams(**{k: np.stack([r[k] for r in rows]) for k in rows[0]})


class SubtaskEnv:
    """The pseudo-reward env of one sub-task (one agent alone), parameterised by TaskParams.

    ``focus``: the fraction of training episodes that start at an initiation state from which the
    latest test's greedy policy was not optimal (``weak``, kept up to date by the trainer through
    ``refocus``), while there is one; the rest start as the task says (``starts``). 0 draws every start
    as before, with the same random numbers."""

    n_agents = 1

    def __init__(self, env: USAREnv, horizon: int, features: str = "factored", n_goals: int = 0,
                 focus: float = 0.0):
        self.height, self.width = env.height, env.width
        self.horizon = int(horizon)
        self.focus = float(focus)
        self.region = env.graph.cell_region
        self.features, self.n_goals = features, int(n_goals)
        self.rubble = Rubble.of(env.layout)
        self.n_modes = self.rubble.n_modes
        self.obs_blocks = (self.height, self.width, 4, 1) + ((self.height * self.width,) if features == "cell" else ()) \
            + (1,) * self.rubble.n_cells + ((self.n_goals,) if self.n_goals else ())
        self.obs_dim = sum(self.obs_blocks)

    def observe(self, pos: jax.Array, direction: jax.Array, flag: jax.Array, goal: jax.Array = 0) -> jax.Array:
        """One agent's features (float32[obs_dim]): one-hot row, col, dir, the task's victim flag, with
        ``features = "cell"`` a one-hot of the cell, on a map with rubble each rubble cell's cleared flag
        (``goal``'s mode), and with ``n_goals`` a one-hot of the goal index (``goal`` // modes). The
        cell one-hot gives every cell weights of its own, so the Q-function need not be composed from row
        and column alone (it is fitted to the 1-step precision optimality needs in far fewer updates:
        benchmarks/README.md)."""
        parts = [jax.nn.one_hot(pos[0], self.height), jax.nn.one_hot(pos[1], self.width),
                 jax.nn.one_hot(direction, 4), jnp.asarray(flag, jnp.float32)[None]]
        if self.features == "cell":
            parts.append(jax.nn.one_hot(pos[0] * self.width + pos[1], self.height * self.width))
        if self.rubble.n_cells:
            mode = goal % self.n_modes
            parts.append(((mode >> jnp.arange(self.rubble.n_cells)) & 1).astype(jnp.float32))
            goal = goal // self.n_modes
        if self.n_goals:
            parts.append(jax.nn.one_hot(goal, self.n_goals))
        return jnp.concatenate(parts)

    def _obs(self, s: SubtaskState):
        return self.observe(s.agent_pos[0], s.agent_dir[0], s.triaged[0], s.goal)

    def reset(self, key, p: TaskParams):
        if not self.focus:
            return self._start(p.starts[jax.random.randint(key, (), 0, p.n_starts)])
        k_start, k_focus, k_weak = jax.random.split(key, 3)
        start = p.starts[jax.random.randint(k_start, (), 0, p.n_starts)]
        n_weak = jnp.sum(p.weak)
        j = jax.random.randint(k_weak, (), 0, jnp.maximum(n_weak, 1))  # the j-th weak state
        weak = p.initiation[jnp.argmax(jnp.cumsum(p.weak) > j)]
        return self._start(jnp.where((jax.random.uniform(k_focus) < self.focus) & (n_weak > 0), weak, start))

    def refocus(self, p: TaskParams, good: jax.Array) -> TaskParams:
        """``p`` with ``weak`` the initiation states not in ``good`` (``coverage``'s second output)."""
        return p.replace(weak=~good & (jnp.arange(good.shape[0]) < p.n_initiation))

    def reset_test(self, key, p: TaskParams):
        return self._start(p.test_starts[jax.random.randint(key, (), 0, p.n_test_starts)])

    def _start(self, start):
        s = EnvState(agent_pos=start[None, :2], agent_dir=start[2:3], triaged=jnp.zeros((1,), bool),
                     t=jnp.zeros((), jnp.int32))
        s = SubtaskState(env=s, goal=start[3])
        return self._obs(s), s

    def _transition(self, pos, direction, action, goal, p: TaskParams):
        """One step of the task's rules from one state: (pos int32[2], dir, triaged, success, index). With
        rubble: the mode's uncleared cells are solid, and a CLEAR task's TRIAGE facing one clears it."""
        solid, mode, k = p.solid, 0, self.rubble.n_cells
        if k:
            mode = goal % self.n_modes
            solid = solid | self.rubble.uncleared(mode)
        new, d, triaged, _ = apply_actions(solid, p.victim_at[goal // self.n_modes], pos[None], direction[None],
                                           jnp.zeros((1,), bool),
                                           action[None])
        target = p.goal_region[goal // self.n_modes]
        success = triaged[0] | (target >= 0) & (jnp.asarray(self.region)[new[0, 0], new[0, 1]] == target)
        if k:
            front = pos + jnp.asarray(DIR_DELTA)[direction]
            inside = (front >= 0).all() & (front[0] < self.height) & (front[1] < self.width)
            front = jnp.clip(front, 0, jnp.array([self.height - 1, self.width - 1]))
            cell = jnp.asarray(self.rubble.index)[front[0], front[1]]
            clear = (p.clears != 0) & (action == TRIAGE) & inside & (cell >= 0) & (((mode >> jnp.maximum(cell, 0)) & 1) == 0)
            cleared = jnp.where(clear, mode | (1 << jnp.maximum(cell, 0)), mode)
            success = success | (p.clears != 0) & ((cleared & p.clears) == p.clears)
            success = success | (action == TRIAGE) & p.wait[goal, pos[0], pos[1]]
            goal = goal - mode + cleared
        return new[0], d[0], triaged[0], success, goal

    def step(self, key, s: SubtaskState, action, p: TaskParams):
        pos, d, triaged, success, goal = self._transition(s.agent_pos[0], s.agent_dir[0], action[0], s.goal, p)
        env = EnvState(agent_pos=pos[None], agent_dir=d[None], triaged=s.triaged | triaged, t=s.t + 1)
        s = s.replace(env=env, goal=goal)
        reward = jnp.where(success, SUCCESS_REWARD, 0.0) + STEP_REWARD
        done = success | (s.t >= self.horizon)
        return self._obs(s), s, reward, done, {"terminated": success, "gamma": p.gamma}

    def optimal_steps_from(self, s: SubtaskState, p: TaskParams) -> jax.Array:
        return p.dist[s.goal, s.agent_pos[0, 0], s.agent_pos[0, 1], s.agent_dir[0]]

    def coverage(self, greedy, p: TaskParams) -> tuple[jax.Array, jax.Array]:
        """``(fraction, good)``: the fraction (float32) of the task's initiation states from which the
        greedy policy reaches the sub-goal on a shortest path, and which ones (bool[K], along
        ``p.initiation``; False on padding), exactly, in one batched call.

        ``greedy(obs float32[obs_dim]) -> action int32[1]``. The policy is evaluated once on every
        (row, col, dir) of the map, for each goal index; a state is good when its greedy action succeeds,
        or leads one step closer (by the planner's distance table ``p.dist``) to a good state. Since the
        distance drops by one along such a chain, iterating to the fixed point (at most max-distance
        rounds) is exact: a good state's greedy rollout takes exactly ``dist`` steps, and any other
        state's does not.
        """
        h, w = self.height, self.width
        n_index = p.dist.shape[0]
        pos, dirs = self._poses()

        def actions_for(goal):  # int32[H * W * 4]: the greedy action in every pose, at index ``goal``
            obs = jax.vmap(self.observe, in_axes=(0, 0, 0, None))(pos, dirs, jnp.zeros_like(dirs, jnp.float32), goal)
            return jax.vmap(greedy)(obs)[:, 0]

        actions = actions_for(0)[None] if n_index == 1 else jax.lax.map(actions_for, jnp.arange(n_index))
        nxt, success = self._successors(actions, p)
        dist = p.dist.reshape(-1)
        closer = dist[nxt] == dist - 1

        def body(c):
            good, _ = c
            new = success | (closer & good[nxt])
            return new, jnp.any(new != good)

        good = jax.lax.while_loop(lambda c: c[1], body, (success, jnp.ones((), bool)))[0]  # over every index
        init = p.initiation
        flat = ((init[:, 3] * h + init[:, 0]) * w + init[:, 1]) * 4 + init[:, 2]
        good = good[flat] & (jnp.arange(init.shape[0]) < p.n_initiation)
        return jnp.sum(good) / p.n_initiation.astype(jnp.float32), good

    def _poses(self):
        """Every (row, col) int32[H * W * 4, 2] and dir, in the flat pose order."""
        rows, cols, dirs = (x.ravel() for x in jnp.meshgrid(jnp.arange(self.height), jnp.arange(self.width),
                                                               jnp.arange(4), indexing="ij"))
        return jnp.stack([rows, cols], -1), dirs

    def _successors(self, actions: jax.Array, p: TaskParams):
        """(next int32[I * H * W * 4], success bool[...]): the flat next state (index, row, col, dir) and the
        task's end, of ``actions`` int32[I, H * W * 4] taken in every state of each index."""
        pos, dirs = self._poses()
        step = jax.vmap(self._transition, in_axes=(0, 0, 0, None, None))
        npos, ndir, _, success, goal = jax.vmap(step, in_axes=(None, None, 0, 0, None))(
            pos, dirs, actions, jnp.arange(actions.shape[0]), p)
        nxt = ((goal * self.height + npos[..., 0]) * self.width + npos[..., 1]) * 4 + ndir
        return nxt.reshape(-1), success.reshape(-1)


def make_learner(env: SubtaskEnv, cfg: DQNConfig) -> IndependentDQN:
    """One DQN per task (the trainer's lanes); the discount comes from the task, via the replay row."""

    def row(transition):
        return {**default_row(transition), "gamma": transition["info"]["gamma"]}

    return IndependentDQN(env.obs_dim, N_ACTIONS, 1, cfg, dqn_target(cfg), row_fn=row, obs_blocks=env.obs_blocks)


def exact_subpolicies(senv: SubtaskEnv, params: TaskParams) -> jax.Array:
    """Exact sub-policies from the planner's distance tables: int32[tasks, I, H, W, 4], a shortest-path
    action per state (the action that ends the task where one does; ties to the lowest), run by
    ``table_act``. In the trained ones' place (``greedy_tables``) they isolate the coordinator (tests,
    benchmarks/coordinators.py)."""
    tables = []
    for k in range(len(params.dist)):
        p = jax.tree.map(lambda x: jnp.asarray(x[k]), params)
        n_index, shape = p.dist.shape[0], p.dist.shape
        after, success = [], []
        for a in range(N_ACTIONS):
            nxt, done = senv._successors(jnp.full((n_index, shape[1] * shape[2] * 4), a, jnp.int32), p)
            after.append(np.asarray(p.dist).reshape(-1)[np.asarray(nxt)]), success.append(np.asarray(done))
        after, success = np.stack(after, -1), np.stack(success, -1)
        best = np.where(success, -1, np.where(after < 0, 10_000, after))
        tables.append(np.argmin(best, -1).astype(np.int32).reshape(shape))
    return jnp.asarray(np.stack(tables))


def greedy_tables(senv: SubtaskEnv, learner: IndependentDQN, params, n_index: int, batch_dims: int = 1) -> jax.Array:
    """Trained sub-policies as tables of their greedy actions: ``params`` with ``batch_dims`` leading axes
    (one per task; [trial, task]: 2) -> int32[*batch, I, H, W, 4] over every goal-and-rubble index
    (``n_index``), cell and facing, the victim flag unset (a running option's victim is never done: its
    option would have ended), run by ``table_act``. The coordinator's macro steps then look an action up
    where they ran a network per agent (benchmarks/README.md, "The coordinator's cost")."""
    index, rows, cols, dirs = (x.ravel() for x in np.meshgrid(np.arange(n_index), np.arange(senv.height),
                                                              np.arange(senv.width), np.arange(4), indexing="ij"))
    obs = jax.vmap(senv.observe, in_axes=(0, 0, None, 0))(jnp.stack([rows, cols], -1), dirs, False, index)
    batch = jax.tree.leaves(params)[0].shape[:batch_dims]
    lanes = jax.tree.map(lambda x: jnp.reshape(x, (-1, *x.shape[batch_dims:])), params)
    greedy = jax.jit(lambda lanes, obs: jax.lax.map(
        lambda p: jax.vmap(lambda o: learner.greedy_act(p, o, None)[0][0])(obs), lanes))
    return greedy(lanes, obs).reshape(*batch, n_index, senv.height, senv.width, 4)


def table_act(senv: SubtaskEnv):
    """``act(table, obs) -> action[1]``: the action of one task's table (``exact_subpolicies``,
    ``greedy_tables``) at the (row, col, facing), rubble flags and goal index of an observation of ``senv``."""
    h, w, n_goals, n_cells = senv.height, senv.width, senv.n_goals, senv.rubble.n_cells
    flags = h + w + 4 + 1 + (h * w if senv.features == "cell" else 0)  # where the rubble flags start

    def act(table, obs):
        r, c, d = jnp.argmax(obs[:h]), jnp.argmax(obs[h:h + w]), jnp.argmax(obs[h + w:h + w + 4])
        goal = jnp.argmax(obs[-n_goals:]) if n_goals else 0  # the goal one-hot is the last block
        mode = jnp.sum(obs[flags:flags + n_cells].astype(jnp.int32) << jnp.arange(n_cells)) if n_cells else 0
        return table[goal * senv.n_modes + mode, r, c, d].reshape(1)

    return act
