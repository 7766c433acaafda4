"""An independent model of the USAR world's rules, written from the text of DESIGN.md's "Contract (fixed)"
and "Contract, part 2: the USAR world" alone: plain Python and numpy, no jax, no code shared with
jaxusar.envs, so that a bug in one is not silently copied into the other (tests/test_contract_model.py
compares the two step for step).

Each rule below quotes the contract sentence it implements. The model does not reproduce the env's random
victim draw: `reset` takes the victim positions (read off the env's reset state) and checks them instead.
Regions are not part of the contract either: the model takes a region grid (int[H, W], -1 exactly on wall
and obstacle cells), e.g. `env.graph.cell_region` or `parse_region_grid` of a region text.
"""

from __future__ import annotations

import dataclasses

import numpy as np

EAST, SOUTH, WEST, NORTH = 0, 1, 2, 3
FORWARD, TURN_LEFT, TURN_RIGHT, TOOL = 0, 1, 2, 3  # TOOL: action 3, TRIAGE in part 1
MEDIC, ENGINEER = 0, 1
REGULAR, CRITICAL = 0, 1
DELTA = np.array([[0, 1], [1, 0], [0, -1], [-1, 0]])  # FORWARD's (d_row, d_col) for EAST, SOUTH, WEST, NORTH

# Layout characters, as the contract names them.
WALL, OBSTACLE, RUBBLE, DRAW_CELL = "#", "X", "r", "?"
AGENT_ROLE = {"A": MEDIC, "E": ENGINEER}
VICTIM_KIND = {"V": REGULAR, "C": CRITICAL}
LAYOUT_CHARS = set("#X.VCAEr?")

# Env defaults: part 1's parameters, then part 2's header keys.
ENV_DEFAULTS = {"horizon": 100, "triage_reward": 100.0, "step_penalty": 0.0, "start_dir": NORTH}
HEADER_DEFAULTS = {
    "random_victims": (0, 0),
    "triage_steps": 1,
    "critical_triage_steps": 1,
    "critical_reward": 300.0,
    "critical_expires": None,
    "view_radius": None,
    "observation": "full",
}


# -- text ------------------------------------------------------------------------------------------
def split_header(text: str) -> tuple[list[str], list[str]]:
    """(header lines, grid rows) of a layout or region text: ';' lines are comments anywhere, the header is
    whatever comes before a line '---' (no such line: no header), blank lines are dropped."""
    lines = [line.rstrip() for line in text.splitlines() if not line.startswith(";")]
    if "---" in lines:
        cut = lines.index("---")
        head, grid = lines[:cut], lines[cut + 1 :]
    else:
        head, grid = [], lines
    return [line for line in head if line.strip()], [row for row in grid if row]


def parse_header(lines: list[str]) -> dict:
    """Header lines `key: value` -> typed values; only the contract's keys are accepted."""
    values = {}
    for line in lines:
        key, sep, value = line.partition(":")
        key, value = key.strip(), value.strip()
        if not sep or key not in HEADER_DEFAULTS:
            raise ValueError(f"not a header line `key: value` with a contract key: {line!r}")
        if key == "random_victims":
            n_regular, n_critical = (int(word) for word in value.split())
            values[key] = (n_regular, n_critical)
        elif key == "observation":
            if value not in ("full", "view"):
                raise ValueError(f"observation: {value!r} is neither 'full' nor 'view'")
            values[key] = value
        elif key in ("critical_expires", "view_radius") and value.lower() == "none":
            values[key] = None
        elif key == "critical_reward":
            values[key] = float(value)
        else:
            values[key] = int(value)
    return values


def parse_region_grid(regions_text: str) -> np.ndarray:
    """int[H, W] region index of a region text (legend lines `letter name kind`, '---', a grid of region
    letters with '#' on wall and obstacle cells): the legend's order, -1 on '#'."""
    legend, grid = split_header(regions_text)
    index = {line.split()[0]: i for i, line in enumerate(legend)}
    index["#"] = -1
    return np.array([[index[ch] for ch in row] for row in grid], dtype=np.int64)


# -- state -----------------------------------------------------------------------------------------
@dataclasses.dataclass
class State:
    """The env state's fields, as numpy arrays (t an int)."""

    agent_pos: np.ndarray  # int[n_agents, 2] (row, col)
    agent_dir: np.ndarray  # int[n_agents]
    triaged: np.ndarray  # bool[n_victims]
    t: int
    victim_pos: np.ndarray  # int[n_victims, 2]
    rubble: np.ndarray  # bool[H, W], rubble not yet cleared
    progress: np.ndarray  # int[n_victims], TRIAGE actions received
    dead: np.ndarray  # bool[n_victims], expired critical victims
    seen: np.ndarray  # bool[H, W], cells the team has seen

    FIELDS = ("agent_pos", "agent_dir", "triaged", "t", "victim_pos", "rubble", "progress", "dead", "seen")

    def copy(self) -> State:
        return State(**{name: np.array(getattr(self, name)) for name in self.FIELDS})

    @classmethod
    def of(cls, state) -> State:
        """A model State from any object with these fields (an env state: pass it through jax.device_get)."""
        return cls(**{name: np.asarray(getattr(state, name)) for name in cls.FIELDS})


# -- the model -------------------------------------------------------------------------------------
class Model:
    """The contract's env on one layout. `params`: horizon, triage_reward, step_penalty, start_dir and any
    header key; a param overrides the layout's header, which overrides the defaults."""

    def __init__(self, layout_text: str, region_grid, **params):
        header_lines, rows = split_header(layout_text)
        unknown = set(params) - set(ENV_DEFAULTS) - set(HEADER_DEFAULTS)
        if unknown:
            raise ValueError(f"unknown params {sorted(unknown)}")
        self.params = {**ENV_DEFAULTS, **HEADER_DEFAULTS, **parse_header(header_lines), **params}
        for name, value in self.params.items():
            setattr(self, name, value)

        if len({len(row) for row in rows}) != 1:
            raise ValueError("layout rows differ in length")
        chars = np.array([list(row) for row in rows])
        if not set(chars.ravel()) <= LAYOUT_CHARS:
            raise ValueError(f"unknown layout characters {sorted(set(chars.ravel()) - LAYOUT_CHARS)}")
        self.chars = chars
        self.blocked = (chars == WALL) | (chars == OBSTACLE)
        self.initial_rubble = chars == RUBBLE
        self.draw_cells = np.argwhere(chars == DRAW_CELL)  # row-major

        # "Agents (A, E) are numbered together in reading order, then fixed victims (V, C) in reading order";
        # drawn victims "follow the fixed victims in index order, regular first".
        self.agent_start = np.argwhere(np.isin(chars, list(AGENT_ROLE)))  # argwhere is row-major
        self.roles = np.array([AGENT_ROLE[chars[r, c]] for r, c in self.agent_start], dtype=np.int64)
        self.fixed_victim_pos = np.argwhere(np.isin(chars, list(VICTIM_KIND)))
        n_regular, n_critical = self.random_victims
        n_fixed, n_drawn = len(self.fixed_victim_pos), n_regular + n_critical
        if n_drawn > len(self.draw_cells):
            raise ValueError(f"{n_drawn} victims to draw among {len(self.draw_cells)} '?' cells")
        self.victim_kind = np.array(
            [VICTIM_KIND[chars[r, c]] for r, c in self.fixed_victim_pos] + [REGULAR] * n_regular + [CRITICAL] * n_critical,
            dtype=np.int64,
        )
        # env.victim_pos: drawn victims' rows are -1
        self.victim_pos = np.concatenate([self.fixed_victim_pos, np.full((n_drawn, 2), -1)]).astype(np.int64)
        self.n_agents, self.n_victims = len(self.agent_start), n_fixed + n_drawn
        self.kind_triage_steps = np.array([self.triage_steps, self.critical_triage_steps])[self.victim_kind]
        self.kind_reward = np.array([self.triage_reward, self.critical_reward])[self.victim_kind]

        self.region = np.asarray(region_grid)
        if self.region.shape != chars.shape or not np.array_equal(self.region < 0, self.blocked):
            raise ValueError("the region grid must match the layout's shape and be -1 exactly on walls and obstacles")

    @classmethod
    def from_texts(cls, layout_text: str, regions_text: str, **params) -> Model:
        return cls(layout_text, parse_region_grid(regions_text), **params)

    @property
    def shape(self) -> tuple[int, int]:
        return self.chars.shape

    # -- pieces of the rules -------------------------------------------------------------------
    def sees(self, pos) -> np.ndarray:
        """bool[H, W]: "a cell in the agent's own region at Chebyshev distance <= view_radius"
        (view_radius none: the whole region)."""
        rows, cols = np.indices(self.shape)
        mask = self.region == self.region[tuple(pos)]
        if self.view_radius is not None:
            mask &= np.maximum(abs(rows - pos[0]), abs(cols - pos[1])) <= self.view_radius
        return mask & (self.region >= 0)

    def front(self, state: State, agent: int) -> tuple[int, int] | None:
        """The cell the agent faces, or None off the grid."""
        r, c = state.agent_pos[agent] + DELTA[state.agent_dir[agent]]
        height, width = self.shape
        return (int(r), int(c)) if 0 <= r < height and 0 <= c < width else None

    def victim_at(self, state: State, cell) -> int | None:
        hits = np.flatnonzero((state.victim_pos == cell).all(axis=1))
        return int(hits[0]) if len(hits) else None

    def tool_target(self, state: State, agent: int):
        """What action 3 of this agent acts on now: ('rubble', cell), ('victim', index) or None (a no-op)."""
        cell = self.front(state, agent)
        if cell is None:
            return None
        if self.roles[agent] == ENGINEER:
            return ("rubble", cell) if state.rubble[cell] else None
        victim = self.victim_at(state, cell)
        if victim is not None and not state.triaged[victim] and not state.dead[victim]:
            return ("victim", victim)
        return None

    def can_enter(self, state: State, agent: int, cell) -> bool:
        """FORWARD's test: in bounds, unblocked, no victim (triaged, dead or not), no other agent (as already
        moved this step), no rubble (as cleared so far this step)."""
        if cell is None or self.blocked[cell] or state.rubble[cell] or self.victim_at(state, cell) is not None:
            return False
        others = np.delete(state.agent_pos, agent, axis=0)
        return not (others == cell).all(axis=1).any()

    def done(self, state: State) -> bool:
        """"Done when every victim is triaged or dead, or at the horizon"."""
        return bool((state.triaged | state.dead).all() or state.t >= self.horizon)

    # -- reset and step ------------------------------------------------------------------------
    def reset(self, victim_pos=None) -> State:
        """The reset state with these victim positions (fixed victims first, then drawn ones), which are
        checked: the fixed ones are the layout's, the drawn ones distinct '?' cells. None: no victims drawn."""
        victim_pos = self.fixed_victim_pos if victim_pos is None else np.asarray(victim_pos)
        n_fixed = len(self.fixed_victim_pos)
        if victim_pos.shape != (self.n_victims, 2):
            raise ValueError(f"victim_pos has shape {victim_pos.shape}, expected {(self.n_victims, 2)}")
        if not np.array_equal(victim_pos[:n_fixed], self.fixed_victim_pos):
            raise ValueError(f"fixed victims at {victim_pos[:n_fixed].tolist()}, layout has {self.fixed_victim_pos.tolist()}")
        drawn = [tuple(cell) for cell in victim_pos[n_fixed:].tolist()]
        draw_cells = {tuple(cell) for cell in self.draw_cells.tolist()}
        if len(set(drawn)) != len(drawn) or not set(drawn) <= draw_cells:
            raise ValueError(f"drawn victims {drawn} are not distinct '?' cells {sorted(draw_cells)}")

        seen = np.zeros(self.shape, bool)
        for pos in self.agent_start:  # "(at reset: from the starts)"
            seen |= self.sees(pos)
        return State(
            agent_pos=self.agent_start.copy(),
            agent_dir=np.full(self.n_agents, self.start_dir),
            triaged=np.zeros(self.n_victims, bool),
            t=0,
            victim_pos=victim_pos.astype(np.int64),
            rubble=self.initial_rubble.copy(),
            progress=np.zeros(self.n_victims, np.int64),
            dead=np.zeros(self.n_victims, bool),
            seen=seen,
        )

    def step(self, state: State, actions) -> tuple[State, float, bool]:
        """(next state, team reward, done); `state` is not changed."""
        actions = [int(a) for a in actions]
        if len(actions) != self.n_agents or not all(0 <= a <= 3 for a in actions):
            raise ValueError(f"actions {actions}: expected {self.n_agents} ints in 0..3")
        s = state.copy()
        was_triaged = s.triaged.copy()
        for agent, action in enumerate(actions):  # "agents act in index order"
            if action == FORWARD:
                cell = self.front(s, agent)
                if self.can_enter(s, agent, cell):
                    s.agent_pos[agent] = cell
            elif action == TURN_LEFT:
                s.agent_dir[agent] = (s.agent_dir[agent] + 3) % 4
            elif action == TURN_RIGHT:
                s.agent_dir[agent] = (s.agent_dir[agent] + 1) % 4
            else:  # "Action 3 is the role's tool"
                target = self.tool_target(s, agent)
                if target is not None and target[0] == "rubble":  # "the cell becomes floor"
                    s.rubble[target[1]] = False
                elif target is not None:  # "adds 1 to its progress, ... triaged when progress reaches ..."
                    victim = target[1]
                    s.progress[victim] += 1
                    if s.progress[victim] >= self.kind_triage_steps[victim]:
                        s.triaged[victim] = True
        # "After every agent has acted, t += 1; then every critical victim not triaged with
        # t >= critical_expires is dead; then the team's seen adds every cell that some agent sees"
        s.t = state.t + 1
        if self.critical_expires is not None and s.t >= self.critical_expires:
            s.dead |= (self.victim_kind == CRITICAL) & ~s.triaged
        for pos in s.agent_pos:
            s.seen |= self.sees(pos)

        newly = s.triaged & ~was_triaged
        reward = float(self.kind_reward[newly].sum()) + float(self.step_penalty)
        return s, reward, self.done(s)
