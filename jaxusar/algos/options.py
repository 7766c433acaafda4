"""Options derived from a map's graph view (paper Sec. IV-B, Table I): nothing map-specific here.

For each room region R: NAVIGATE-TO-R (termination: the agent is in R). Its initiation set depends
on ``navigation``: ``adjacent`` (the paper, Sec. IV-B): the agent is in a region adjacent to R;
``chained``: the agent is in any other region from which R can be reached; the option then runs the
adjacent-region sub-policies along the region graph's shortest path (``next_hop``; the paper's
"chaining options", its future work); ``goal``: the same initiation set, run by one goal-conditioned
sub-policy. For each victim v, in room R: TRIAGE-v (initiation: the agent
is in R and v is not yet triaged; termination: v is triaged). On the two-rooms map this is Table I:
NAVIGATE-TO-TOP-ROOM, NAVIGATE-TO-BOTTOM-ROOM, TRIAGE-TOP-VICTIM, TRIAGE-BOTTOM-VICTIM.

Rubble (contract part 2) adds, for each group g of touching rubble cells, CLEAR-g: engineers only,
offered in the regions that hold or touch a cell of g while g is not cleared, ending when every cell of
g is cleared. TRIAGE is for medics only. Where rubble lies, every option is also offered only where the
rubble not yet cleared leaves a way: from every open cell of the agent's region, the room (NAVIGATE),
the victim (TRIAGE) or a cell next to the group (CLEAR) can be reached with every uncleared group's
cells solid (``open_from``, one table per *config*: the bitmask of cleared groups). A NAVIGATE whose
room rubble cuts off goes instead to a cell near the rubble in its way and waits there
(``waiting_cells``), so a medic can be at the doorway when an engineer clears it (two_rooms_rubble's
optimum has a medic walk to the rubble before any is cleared); the cell leaves the engineer another cell
to clear the rubble from and a way to it (agents block each other: at a one-wide doorway the medic waits
a step back).

The method sees rubble in a room's doorway as the hall's (``doorway_rubble_regions``, ``method_env``): a
room starts past the rubble at its edge, so NAVIGATE-TO-R ends past it, and an engineer that cleared
the way and walked in stands aside instead of in the doorway (two_rooms_rubble's optimum does that).
The env's own region grid (what "view" shows) is unchanged.

Victims drawn at reset (contract part 2): the places a victim may lie are *slots* (``victim_slots``: a
fixed victim's cell or a '?' cell). A slot is *done* once the team knows it holds no victim to save:
under "view" once it has been seen holding none (empty, triaged or dead); under full observation as
soon as it holds none. A medic's NAVIGATE-TO-R is offered while a slot of R is not done (nothing else
is there to go for; an engineer's always, to step out of the way). TRIAGE-IN-R, one per room R that
holds slots, is offered to a medic in R likewise and ends when every slot of R is done; its sub-policy
(one task per room, told the slot as its goal) works on one slot at a time: a known critical victim
first, then a known one, then an unseen slot, the nearest first (``coordinator.MacroEnv.target_slot``).
Under "view" that is also the search: a medic sent to an unseen slot sees it on the way, and goes on
once it is seen empty. A critical victim that needs several TRIAGE actions gets them: the sub-policy's
input does not change until it is triaged.

Initiation and termination are pure functions of the abstract state (agent region, triaged flags, the
cleared groups), usable inside jit.
"""

from __future__ import annotations

import copy
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.ndimage

from jaxusar.config import OPTION_KINDS, ConfigError
from jaxusar.envs.graph import RegionGraph
from jaxusar.envs.layout import ENGINEER, MEDIC, _neighbours

NAVIGATE, TRIAGE, CLEAR = 0, 1, 2
MAX_RUBBLE_CELLS = 6  # sub-policies see which rubble cells are cleared: 2^6 modes per task at most


@dataclasses.dataclass(frozen=True, eq=False)
class Rubble:
    """A map's rubble as the hierarchical method sees it (numpy, static). ``cells`` int32[K, 2] in
    reading order; ``group`` int32[K]: touching cells (4-neighbours) share a group, numbered by first
    cell; ``index`` int32[H, W]: each rubble cell's k, -1 elsewhere. A *mode* is the bitmask of cleared
    cells (bit k: cell k cleared; 0 at reset), a *config* the bitmask of fully cleared groups."""

    cells: np.ndarray
    group: np.ndarray
    index: np.ndarray

    @classmethod
    def of(cls, layout) -> "Rubble":
        cells = np.argwhere(layout.rubble).astype(np.int32).reshape(-1, 2)
        index = np.full(layout.shape, -1, np.int32)
        index[tuple(cells.T)] = np.arange(len(cells))
        label, _ = scipy.ndimage.label(layout.rubble)  # 4-connected, numbered in reading order from 1
        return cls(cells, (label[tuple(cells.T)] - 1).astype(np.int32), index)

    n_cells = property(lambda self: len(self.cells))
    n_groups = property(lambda self: int(self.group.max()) + 1 if len(self.group) else 0)
    n_modes = property(lambda self: 2 ** self.n_cells)
    n_configs = property(lambda self: 2 ** self.n_groups)

    @property
    def group_bits(self) -> np.ndarray:
        """int32[G]: the mode bits of each group's cells."""
        return np.array([sum(1 << int(k) for k in np.flatnonzero(self.group == g)) for g in range(self.n_groups)],
                        np.int32)

    def mode_of(self, rubble) -> jax.Array:
        """int32: the mode of a state's ``rubble`` bool[H, W] (its cells not yet cleared)."""
        cleared = ~rubble[self.cells[:, 0], self.cells[:, 1]]
        return jnp.sum(cleared.astype(jnp.int32) << jnp.arange(self.n_cells, dtype=jnp.int32))

    def config_of(self, mode):
        """The config (bitmask of fully cleared groups) of a mode (numpy or jax ints)."""
        bits = self.group_bits
        return sum(((mode & int(b)) == int(b)) * (1 << g) for g, b in enumerate(bits)) if len(bits) else 0 * mode

    def uncleared(self, mode) -> jax.Array:
        """bool[H, W]: the rubble cells not cleared in ``mode`` (a traced int)."""
        index = jnp.asarray(self.index)
        return (index >= 0) & (((mode >> jnp.maximum(index, 0)) & 1) == 0)

    def uncleared_in_config(self, config: int) -> np.ndarray:
        """bool[H, W]: the cells of the groups not cleared in ``config`` (numpy)."""
        solid = np.zeros(self.index.shape, bool)
        for k, (r, c) in enumerate(self.cells):
            solid[r, c] = not (config >> int(self.group[k])) & 1
        return solid


@dataclasses.dataclass(frozen=True, eq=False)
class Options:
    """The option set of a map. Arrays are numpy (static), one entry per option."""

    names: tuple[str, ...]
    kind: np.ndarray      # int32[O]: NAVIGATE, TRIAGE or CLEAR
    region: np.ndarray    # int32[O]: the room to reach (NAVIGATE), the victim's room (TRIAGE), -1 (CLEAR)
    victim: np.ndarray    # int32[O]: the victim to triage, -1 for the others
    starts_from: np.ndarray  # bool[R, R]: NAVIGATE-TO-r may start in region q where starts_from[q, r]
    group: np.ndarray | None = None     # int32[O]: the rubble group to clear (CLEAR), -1 for the others
    open_from: np.ndarray | None = None  # bool[C, R, O]: o may start in region q under config c (module doc)
    rubble: Rubble | None = None
    slot_flag: np.ndarray | None = None  # int32[S]: drawn victims: each slot's room's TRIAGE flag; None: flag = victim

    def __post_init__(self):  # a map without rubble: one config, the plain rules
        if self.group is None:
            object.__setattr__(self, "group", np.full(len(self.names), -1, np.int32))
        if self.open_from is None:
            regions = np.arange(len(self.starts_from))[:, None]
            open_from = np.where(self.kind == NAVIGATE, self.starts_from[:, self.region], regions == self.region)
            object.__setattr__(self, "open_from", open_from[None])

    @property
    def n(self) -> int:
        return len(self.names)

    def only(self, kinds: tuple[str, ...]) -> "Options":
        """The options of the named ``kinds`` (``OPTION_KINDS``), in the same order."""
        keep = np.isin(self.kind, [OPTION_KINDS.index(k) for k in kinds])
        return Options(tuple(np.asarray(self.names)[keep]), self.kind[keep], self.region[keep], self.victim[keep],
                       self.starts_from, self.group[keep], self.open_from[..., keep], self.rubble, self.slot_flag)

    @property
    def role(self) -> np.ndarray:
        """int32[O]: the role an option is for (MEDIC: TRIAGE, ENGINEER: CLEAR), -1: any (NAVIGATE)."""
        return np.select([self.kind == TRIAGE, self.kind == CLEAR], [MEDIC, ENGINEER], -1).astype(np.int32)

    def can_initiate(self, agent_region: jax.Array, triaged: jax.Array, config: jax.Array = 0,
                     role: jax.Array = MEDIC) -> jax.Array:
        """bool[O]: options whose initiation set holds for an agent of ``role`` in ``agent_region``, with
        the groups of ``config`` cleared; ``triaged``: each TRIAGE option's flag, its victim triaged (where
        victims are drawn, its room done: ``coordinator.MacroEnv.flags``)."""
        kind, role_of = jnp.asarray(self.kind), jnp.asarray(self.role)
        victim_open = ~triaged[jnp.maximum(jnp.asarray(self.victim), 0)]
        group_open = ((config >> jnp.maximum(jnp.asarray(self.group), 0)) & 1) == 0
        ok = jnp.asarray(self.open_from)[config, agent_region] & ((role_of < 0) | (role_of == role))
        room_open = True
        if self.slot_flag is not None:  # drawn victims: a medic's NAVIGATE-TO-R while R may hold a victim to save
            flag = jnp.asarray(self.room_flag)  # (an engineer's anywhere: it may have to step out of the way)
            room_open = (flag >= 0) & ~triaged[jnp.maximum(flag, 0)] | (role == ENGINEER)
        return ok & jnp.where(kind == TRIAGE, victim_open, jnp.where(kind == CLEAR, group_open, room_open))

    @property
    def room_flag(self) -> np.ndarray:
        """int32[O]: drawn victims: the TRIAGE flag of each NAVIGATE option's room (-1: none, or not NAVIGATE)."""
        triage = {int(r): int(v) for k, r, v in zip(self.kind, self.region, self.victim) if k == TRIAGE}
        return np.array([triage.get(int(r), -1) if k == NAVIGATE else -1 for k, r in zip(self.kind, self.region)],
                        np.int32)

    def terminated(self, option: jax.Array, agent_region: jax.Array, triaged: jax.Array,
                   config: jax.Array = 0) -> jax.Array:
        """bool: option ``option`` (an index) has reached its termination condition."""
        kind, region, victim, group = (jnp.asarray(a)[option] for a in (self.kind, self.region, self.victim, self.group))
        return jnp.select([kind == NAVIGATE, kind == TRIAGE],
                          [agent_region == region, triaged[jnp.maximum(victim, 0)]],
                          ((config >> jnp.maximum(group, 0)) & 1) == 1)


def check_option_kinds(kinds: tuple[str, ...], env) -> None:
    """A one-line ConfigError where ``kinds`` (``hierarchical.option_kinds``; empty: every kind the map
    offers) names a kind ``env`` cannot offer, or leaves the team no way to save a victim."""
    where = f"hierarchical.option_kinds={','.join(kinds)}"
    if kinds and "triage" not in kinds:
        raise ConfigError(f"{where}: without triage options no victim can be saved")
    if "clear" in kinds and not (env.has_rubble and env.has_engineers):
        lacks = "no rubble" if not env.has_rubble else "no engineer ('E')"
        raise ConfigError(f"{where}: clear options need rubble and an engineer, and map {env.layout.name!r} has {lacks}")
    if "search" in kinds and env.observation != "view":
        raise ConfigError(f"{where}: search options need observation=view (a room is searched once every cell of it "
                          f"was seen), and map {env.layout.name!r} is observed in full")
    if "search" in kinds:
        raise ConfigError(f"{where}: the hierarchical method builds no search options: under observation=view "
                          "TRIAGE-IN-R searches (a medic sent to a room's unseen slot sees it on the way)")


def room_label(name: str) -> str:
    return name.upper().replace("_", "-")


def next_hop(adjacency: np.ndarray) -> np.ndarray:
    """int32[R, R]: the region after q on a shortest path (fewest regions) from q to r; -1 where r == q
    or r cannot be reached. Ties go to the lowest region index, so the table is deterministic."""
    n = len(adjacency)
    hop = np.full((n, n), -1, np.int32)
    for r in range(n):  # breadth-first from the goal r: a region's hop is its first neighbour one layer closer
        dist = np.full(n, -1)
        dist[r], frontier = 0, [r]
        while frontier:
            nxt = []
            for q in frontier:
                for p in np.flatnonzero(adjacency[q]):
                    if dist[p] < 0:
                        dist[p] = dist[q] + 1
                        nxt.append(p)
            frontier = nxt
        for q in range(n):
            if q != r and dist[q] > 0:
                hop[q, r] = next(p for p in np.flatnonzero(adjacency[q]) if dist[p] == dist[q] - 1)
    return hop


NAVIGATIONS = ("adjacent", "chained", "goal")


def doorway_rubble_regions(layout) -> np.ndarray:
    """int32[H, W]: ``layout.region`` with each rubble group (4-connected) that lies in one room and touches
    another region given to that region (a hall first, then the lowest index), unless that would empty the
    room or split it in two: its doorway's rubble is the way in, not the room."""
    region = layout.region.copy()
    if layout.rubble is None:
        return region
    kinds = layout.region_kinds
    label, n = scipy.ndimage.label(layout.rubble)
    for g in range(1, n + 1):
        group = label == g
        room = set(region[group].tolist())
        if len(room) != 1 or kinds[next(iter(room))] != "room":
            continue
        room = room.pop()
        around = region[_neighbours(group)]
        others = set(around[(around >= 0) & (around != room)].tolist())
        if not others:
            continue
        rest = (region == room) & ~group
        if not rest.any() or scipy.ndimage.label(rest)[1] != scipy.ndimage.label(region == room)[1]:
            continue
        region[group] = min(others, key=lambda q: (kinds[q] != "hall", q))
    return region


def victim_slots(layout) -> np.ndarray:
    """int32[S, 2]: every cell a victim may lie on, the method's *slots*: the fixed victims' cells, then the
    '?' cells victims are drawn on (reading order). On a map without drawn victims, the victims' cells."""
    return np.concatenate([layout.victim_pos, layout.random_cells]).astype(np.int32).reshape(-1, 2)


def method_env(env):
    """``env`` as the hierarchical method plans on it: the same env (its step, rules and observations
    untouched) with a layout in which

    * ``doorway_rubble_regions`` gives the region grid (rubble in a doorway is the hall's);
    * where victims are drawn, ``victim_pos`` lists the ``victim_slots`` (a TRIAGE option per slot, told
      its cell) and the '?' cells are obstacles, so that no sub-policy's way runs through a cell where
      a victim may lie (victims block movement; their places vary).

    ``env`` itself where that changes nothing (every map without rubble or drawn victims). The regions
    may change only under full observation: under "view" they are what an agent sees."""
    layout, region = env.layout, doorway_rubble_regions(env.layout)
    changes = {}
    if not np.array_equal(region, layout.region):
        assert env.observation == "full", "the method's regions would change what the agents see"
        changes["region"] = region
    if len(layout.random_cells):
        slots = victim_slots(layout)
        obstacle = layout.obstacle.copy()
        obstacle[tuple(layout.random_cells.T)] = True
        kind = np.concatenate([layout.victim_kind, np.zeros(len(layout.random_cells), layout.victim_kind.dtype)])
        changes.update(victim_pos=slots, victim_kind=kind, obstacle=obstacle)
    if not changes:
        return env
    view = copy.copy(env)  # the env's own arrays (``victim_pos``, ``_solid``, ...) stay: it steps as before
    view.layout = dataclasses.replace(layout, **changes)
    view.graph = RegionGraph(view.layout)
    return view


def waiting_cells(solid: np.ndarray, uncleared: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """bool[H, W]: where a NAVIGATE to the cells ``goal`` waits while ``uncleared`` rubble cuts it off.
    The rubble in its way: uncleared cells next to an open cell that has no way to the goal now and is
    farther from it than the rubble cell on the map with every rubble cleared; those open cells are where an
    engineer on this side clears it (its *clearing cells*). An agent waiting must leave an engineer a
    clearing cell and a way to it, since agents block each other: the waiting cells are the open cells cut
    off from the goal nearest the clearing cells (the clearing cells themselves first) that leave another
    clearing cell free and split no open area in two; where none does, the clearing cells.
    ``solid``: blocked cells, rubble aside."""
    from jaxusar.planning import steps_to_goal

    no_victim = np.full(solid.shape, -1, np.int32)
    far = np.iinfo(np.int32).max
    cleared = steps_to_goal(solid, no_victim, goal_region_mask=goal)
    near = np.where(cleared < 0, far, cleared).min(-1)  # steps to the goal per cell, rubble cleared
    open_cells = ~(solid | uncleared)
    cut = (steps_to_goal(solid | uncleared, no_victim, goal_region_mask=goal) < 0).all(-1) & open_cells
    clearing = np.zeros(solid.shape, bool)
    for r, c in np.argwhere(uncleared):
        for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
            i, j = r + dr, c + dc
            if 0 <= i < solid.shape[0] and 0 <= j < solid.shape[1] and cut[i, j] and near[r, c] < near[i, j]:
                clearing[i, j] = True
    layer, done = clearing, np.zeros(solid.shape, bool)
    while layer.any():  # breadth-first out from the clearing cells, through the cut-off cells
        ok = np.zeros(solid.shape, bool)
        for i, j in np.argwhere(layer):
            cell = np.zeros(solid.shape, bool)
            cell[i, j] = True
            label, _ = scipy.ndimage.label(open_cells & ~cell)  # 4-connected areas, 0 elsewhere
            around = np.unique(label[_neighbours(cell) & open_cells])  # one area: waiting there splits none
            ok[i, j] = len(around) == 1 and (clearing & (label == around[0])).any()
        if ok.any():
            return ok
        done |= layer
        layer = _neighbours(layer) & cut & ~done
    return clearing


def _in_a_room(graph: RegionGraph, r: int, who: str) -> None:
    """A ConfigError unless region ``r``, where ``who`` (a victim) lies, is a room: TRIAGE options are rooms'."""
    if graph.kinds[r] != "room":
        raise ConfigError(f"{who} in {graph.names[r]!r}, a {graph.kinds[r]}: triage options need a room (mark its "
                          "cells as a room in the map's region grid)")


def options_from_graph(graph: RegionGraph, navigation: str = "adjacent", env=None,
                       kinds: tuple[str, ...] = ()) -> Options:
    """The options of a map's region graph; with ``env`` (a ``USAREnv``) that holds rubble, also its
    CLEAR options and the rubble-aware ``open_from`` (module doc). ``kinds`` (``OPTION_KINDS``; empty:
    all): only options of these kinds."""
    if navigation not in NAVIGATIONS:
        raise ValueError(f"navigation {navigation!r}: one of {NAVIGATIONS}")
    names, kind, region, victim = [], [], [], []
    for r in graph.rooms:
        names.append(f"NAVIGATE-TO-{room_label(graph.names[r])}")
        kind.append(NAVIGATE), region.append(r), victim.append(-1)
    drawn = env is not None and len(env.layout.random_cells) > 0
    slot_flag = None
    if drawn:  # one TRIAGE-IN-R per room that holds a slot; its flag: the room done
        rooms = sorted(set(graph.victim_region.tolist()), key=list(graph.victim_region).index)
        for k, r in enumerate(rooms):
            _in_a_room(graph, r, "a victim may lie")
            names.append(f"TRIAGE-IN-{room_label(graph.names[r])}")
            kind.append(TRIAGE), region.append(int(r)), victim.append(k)
        slot_flag = np.array([rooms.index(r) for r in graph.victim_region], np.int32)
    for v, r in enumerate([] if drawn else graph.victim_region):
        _in_a_room(graph, r, f"victim {v} lies")
        in_room = np.flatnonzero(graph.victim_region == r)
        room = graph.names[r]
        if len(in_room) == 1 and room.endswith("_room"):
            names.append(f"TRIAGE-{room_label(room[: -len('_room')])}-VICTIM")  # paper's Table I names
        else:
            names.append(f"TRIAGE-VICTIM-{v}-IN-{room_label(room)}")
        kind.append(TRIAGE), region.append(int(r)), victim.append(v)
    starts_from = graph.adjacency if navigation == "adjacent" else next_hop(graph.adjacency) >= 0
    plain = Options(tuple(names), np.asarray(kind, np.int32), np.asarray(region, np.int32),
                    np.asarray(victim, np.int32), starts_from, slot_flag=slot_flag)
    options = plain if env is None or not env.has_rubble else _with_rubble(plain, graph, env)
    return options.only(kinds) if kinds else options


def _with_rubble(plain: Options, graph: RegionGraph, env) -> Options:
    """``plain`` with a CLEAR option per rubble group and ``open_from`` per config (module doc)."""
    from jaxusar.planning import steps_to_goal

    rubble = Rubble.of(env.layout)
    if rubble.n_cells > MAX_RUBBLE_CELLS:
        raise ConfigError(f"map {env.layout.name!r} has {rubble.n_cells} rubble cells: the hierarchical method's "
                          f"sub-policies handle at most {MAX_RUBBLE_CELLS} (they see each cell cleared or not)")
    region = graph.cell_region
    beside = np.zeros((rubble.n_groups,) + env.layout.shape, bool)  # the open cells next to each group
    touches = np.zeros((graph.n_regions, rubble.n_groups), bool)  # the regions holding or touching it
    for (r, c), g in zip(rubble.cells, rubble.group):
        for dr, dc in ((0, 0), (0, 1), (1, 0), (0, -1), (-1, 0)):
            i, j = r + dr, c + dc
            if 0 <= i < region.shape[0] and 0 <= j < region.shape[1] and region[i, j] >= 0:
                touches[region[i, j], g] = True
                beside[g, i, j] |= not env.layout.rubble[i, j]
    names = plain.names + tuple(f"CLEAR-RUBBLE-{g}" for g in range(rubble.n_groups))
    kind = np.concatenate([plain.kind, np.full(rubble.n_groups, CLEAR, np.int32)])
    opt_region = np.concatenate([plain.region, np.full(rubble.n_groups, -1, np.int32)])
    victim = np.concatenate([plain.victim, np.full(rubble.n_groups, -1, np.int32)])
    group = np.concatenate([np.full(plain.n, -1, np.int32), np.arange(rubble.n_groups, dtype=np.int32)])
    no_victim = np.full(env.layout.shape, -1, np.int32)
    plan = env.layout.blocked.copy()  # blocked, or where a victim may lie (``method_env``)
    plan[tuple(env.layout.victim_pos.T)] = True
    open_from = np.zeros((rubble.n_configs, graph.n_regions, len(names)), bool)
    for config in range(rubble.n_configs):
        uncleared = rubble.uncleared_in_config(config)
        solid = plan | uncleared
        open_cells = ~solid & (region >= 0)

        def from_all_cells(dist):  # bool[R]: every open cell of the region (there is one) reaches the goal
            ok = (dist >= 0).all(-1) | ~open_cells
            return np.array([open_cells[region == q].any() and ok[region == q].all() for q in range(graph.n_regions)])

        for o in range(len(names)):
            if kind[o] == NAVIGATE:  # the room, or where rubble in the way is waited for
                room = region == opt_region[o]
                wait = waiting_cells(plan, uncleared, room)
                dist = steps_to_goal(solid, no_victim, goal_region_mask=room | wait)
                open_from[config, :, o] = plain.starts_from[:, opt_region[o]] & from_all_cells(dist)
            elif kind[o] == TRIAGE:
                target = no_victim.copy()  # the planner triages victim 0: the option's, or any slot of its room
                slots = [victim[o]] if plain.slot_flag is None else np.flatnonzero(plain.slot_flag == victim[o])
                target[tuple(env.layout.victim_pos[slots].T)] = 0
                reach = from_all_cells(steps_to_goal(solid, target, triage=True))
                open_from[config, opt_region[o], o] = reach[opt_region[o]]
            else:
                reach = from_all_cells(steps_to_goal(solid, no_victim, goal_region_mask=beside[group[o]] & ~solid))
                open_from[config, :, o] = touches[:, group[o]] & reach
    return Options(names, kind, opt_region, victim, plain.starts_from, group, open_from, rubble, plain.slot_flag)
