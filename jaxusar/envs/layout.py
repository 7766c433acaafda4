"""ASCII layouts and region grids -> static numpy arrays (validated once, outside jit).

A map is two text files in ``jaxusar/envs/layouts/``:

``NAME.txt``          the layout. Legend (``LAYOUT_CHARS``): ``#`` wall, ``X`` obstacle, ``.`` floor,
                      ``V`` regular victim, ``C`` critical victim, ``A`` medic start, ``E`` engineer
                      start, ``r`` rubble, ``?`` a cell where a victim may be drawn. Agents (``A``, ``E``)
                      are numbered together in reading order, then the fixed victims (``V``, ``C``) in
                      reading order; victims drawn at reset follow them (DESIGN.md, contract part 2).
                      Header lines ``key: value`` before ``---`` set the map's env defaults
                      (``HEADER_KEYS``; an ``envs.make`` override wins).
``NAME.regions.txt``  the region grid (the paper's graph view, Fig. 3): one letter per cell, ``#``
                      exactly on the wall and obstacle cells; its header names each letter
                      (``T top_room room``; the kind is ``room`` or ``hall``). A map without one is
                      segmented from its layout (``mapgen.segment``: rooms are the areas wide enough
                      for 3x3 open cells, corridors and doorways are hall; rubble and ``?`` cells are
                      open floor there), and the grid is written beside it to inspect and edit.
``NAME.settings.yaml`` optional: config settings that belong to this map (they name its tasks), merged
                      over an algorithm's defaults in every run on it (``jaxusar.config.load``).

Each file may start with a header that ends at a line ``---``; header lines starting with ``;``
are comments. A file without ``---`` is all grid.
"""

from __future__ import annotations

import dataclasses
import numbers
import warnings
from pathlib import Path

import numpy as np

LAYOUT_DIR = Path(__file__).parent / "layouts"
LAYOUT_CHARS = {"#": "wall", "X": "obstacle", ".": "floor", "V": "regular victim", "C": "critical victim",
                "A": "medic start", "E": "engineer start", "r": "rubble", "?": "cell where a victim may be drawn"}
MEDIC, ENGINEER = 0, 1
ROLE_NAMES = ("MEDIC", "ENGINEER")
REGULAR, CRITICAL = 0, 1
KIND_NAMES = ("REGULAR", "CRITICAL")
REGION_KINDS = ("room", "hall")
OBSERVATIONS = ("full", "view")
# Header keys of a layout and their defaults (DESIGN.md, contract part 2); None = "none".
HEADER_KEYS = {"random_victims": (0, 0), "triage_steps": 1, "critical_triage_steps": 1, "critical_reward": 300.0,
               "critical_expires": None, "view_radius": None, "observation": "full"}


class LayoutError(ValueError):
    """A layout or region grid that cannot describe a valid map."""


@dataclasses.dataclass(frozen=True, eq=False)
class Layout:
    """A parsed, validated map. All arrays are numpy (static: closed over by the jitted env).

    Attributes:
      name:          the map's name.
      wall:          bool[H, W], wall cells.
      obstacle:      bool[H, W], obstacle cells.
      agent_start:   int32[n_agents, 2], (row, col) of each agent's start ('A' and 'E'), row-major order.
      victim_pos:    int32[n_fixed, 2], (row, col) of each fixed victim ('V' and 'C'), row-major order.
      region:        int32[H, W], region index of each cell, -1 on wall and obstacle cells.
      region_names:  tuple[str], one per region, in order of first appearance in the header.
      region_kinds:  tuple[str], ``room`` or ``hall`` per region.
      rubble:        bool[H, W], rubble cells ('r') at reset.
      roles:         int32[n_agents], MEDIC (0, 'A') or ENGINEER (1, 'E').
      victim_kind:   int32[n_fixed], REGULAR (0, 'V') or CRITICAL (1, 'C') per fixed victim.
      random_cells:  int32[n_cells, 2], the '?' cells (row-major), where victims are drawn at reset.
      header:        dict, the map's env defaults from its header (``HEADER_KEYS``; only keys it sets).
    """

    name: str
    wall: np.ndarray
    obstacle: np.ndarray
    agent_start: np.ndarray
    victim_pos: np.ndarray
    region: np.ndarray
    region_names: tuple[str, ...]
    region_kinds: tuple[str, ...]
    rubble: np.ndarray | None = None
    roles: np.ndarray | None = None
    victim_kind: np.ndarray | None = None
    random_cells: np.ndarray | None = None
    header: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):  # part-1 layouts (and code that builds one by hand) leave the part-2 fields out
        defaults = {"rubble": np.zeros(self.wall.shape, bool), "roles": np.zeros(len(self.agent_start), np.int32),
                    "victim_kind": np.zeros(len(self.victim_pos), np.int32),
                    "random_cells": np.zeros((0, 2), np.int32)}
        for field, value in defaults.items():
            if getattr(self, field) is None:
                object.__setattr__(self, field, value)

    @property
    def shape(self) -> tuple[int, int]:
        return self.wall.shape

    @property
    def blocked(self) -> np.ndarray:
        return self.wall | self.obstacle

    def to_ascii(self) -> str:
        """The layout's grid as the ASCII it was parsed from (without its header)."""
        grid = np.full(self.shape, ".", dtype="<U1")
        grid[self.wall] = "#"
        grid[self.obstacle] = "X"
        grid[self.rubble] = "r"
        for r, c in self.random_cells:
            grid[r, c] = "?"
        for (r, c), kind in zip(self.victim_pos, self.victim_kind):
            grid[r, c] = "VC"[kind]
        for (r, c), role in zip(self.agent_start, self.roles):
            grid[r, c] = "AE"[role]
        return "\n".join("".join(row) for row in grid)

    def subset(self, agents=None, victims=None) -> "Layout":
        """The same map with only the given agents and fixed victims (by index; order kept).

        Used for the paper's sub-tasks, where "the other agents and victims are removed" (Sec. IV-B).
        Naming ``victims`` also removes the victims drawn at reset (their '?' cells become floor).
        """
        agents = range(len(self.agent_start)) if agents is None else list(agents)
        drawn = {}
        if victims is not None:
            drawn = {"random_cells": np.zeros((0, 2), np.int32),
                     "header": {k: v for k, v in self.header.items() if k != "random_victims"}}
        victims = range(len(self.victim_pos)) if victims is None else list(victims)
        return dataclasses.replace(
            self,
            agent_start=self.agent_start[list(agents)].reshape(-1, 2),
            roles=self.roles[list(agents)],
            victim_pos=self.victim_pos[list(victims)].reshape(-1, 2),
            victim_kind=self.victim_kind[list(victims)],
            **drawn,
        )


def header_value(key: str, value, where: str):
    """A map setting checked and normalised (``HEADER_KEYS``): from a layout header (a string) or an
    ``envs.make`` override. Raises LayoutError naming ``where`` and the key."""
    if key not in HEADER_KEYS:
        raise LayoutError(f"{where}: unknown key {key!r}; known keys: {', '.join(HEADER_KEYS)}")

    def bad(expected):
        return LayoutError(f"{where}: {key}={value!r}: expected {expected}")

    def integer(x, least):
        if isinstance(x, str):
            try:
                x = int(x.strip())
            except ValueError:
                raise bad(f"an integer >= {least}") from None
        if isinstance(x, bool) or not isinstance(x, numbers.Integral) or x < least:
            raise bad(f"an integer >= {least}")
        return int(x)

    if key == "random_victims":
        parts = value.split() if isinstance(value, str) else value
        if not isinstance(parts, (list, tuple)) or len(parts) != 2:
            raise bad("two integers >= 0: N_REGULAR N_CRITICAL")
        return tuple(integer(x, 0) for x in parts)
    if key in ("triage_steps", "critical_triage_steps"):
        return integer(value, 1)
    if key in ("critical_expires", "view_radius"):
        if value is None or (isinstance(value, str) and value.strip().lower() == "none"):
            return None
        return integer(value, 1 if key == "critical_expires" else 0)
    if key == "critical_reward":
        try:
            number = float(value.strip() if isinstance(value, str) else value)
        except (TypeError, ValueError):
            raise bad("a number") from None
        if isinstance(value, bool) or not np.isfinite(number):
            raise bad("a finite number")
        return number
    if value not in OBSERVATIONS:  # observation
        raise bad(f"one of {', '.join(OBSERVATIONS)}")
    return value


def _parse_header(lines: list[str], name: str) -> dict:
    header = {}
    for line in lines:
        key, colon, value = line.partition(":")
        key = key.strip()
        if not colon or not key:
            raise LayoutError(f"layout {name!r}: header line {line!r} is not 'key: value' (or a ';' comment)")
        if key in header:
            raise LayoutError(f"layout {name!r}: header key {key!r} is set twice")
        header[key] = header_value(key, value.strip(), f"layout {name!r} header")
    return header


def _split_header(text: str, what: str) -> tuple[list[str], list[str]]:
    lines = text.splitlines()
    if "---" in [ln.strip() for ln in lines]:
        cut = [ln.strip() for ln in lines].index("---")
        header, grid = lines[:cut], lines[cut + 1 :]
    else:
        header, grid = [], lines
    header = [ln.strip() for ln in header if ln.strip() and not ln.strip().startswith(";")]
    grid = [ln.rstrip("\n\r") for ln in grid]
    while grid and not grid[-1].strip():
        grid.pop()
    while grid and not grid[0].strip():
        grid.pop(0)
    if not grid:
        raise LayoutError(f"{what}: no grid rows found")
    widths = {len(row) for row in grid}
    if len(widths) != 1:
        bad = next(i for i, row in enumerate(grid) if len(row) != len(grid[0]))
        raise LayoutError(
            f"{what}: ragged grid: row 0 has {len(grid[0])} columns but row {bad} has {len(grid[bad])}"
        )
    return header, grid


def parse_layout(text: str, regions_text: str, name: str = "<string>") -> Layout:
    """Parse and validate a layout and its region grid. Raises LayoutError naming the problem."""
    header_lines, grid = _split_header(text, f"layout {name!r}")
    header = _parse_header(header_lines, name)
    chars = np.array([list(row) for row in grid])
    unknown = sorted(map(str, set(chars.ravel()) - set(LAYOUT_CHARS)))  # str: np.str_ reprs as np.str_(...)
    if unknown:
        r, c = np.argwhere(chars == unknown[0])[0]
        raise LayoutError(
            f"layout {name!r}: unknown character {unknown[0]!r} at row {r}, col {c}; "
            f"legend: " + ", ".join(f"{k!r} {v}" for k, v in LAYOUT_CHARS.items())
        )
    wall, obstacle = chars == "#", chars == "X"
    agent_start = np.argwhere(np.isin(chars, ["A", "E"])).astype(np.int32)  # argwhere is row-major order
    victim_pos = np.argwhere(np.isin(chars, ["V", "C"])).astype(np.int32)
    if len(agent_start) == 0:
        raise LayoutError(f"layout {name!r}: no agent start ('A' medic or 'E' engineer)")

    region, names, kinds = _parse_regions(regions_text, chars.shape, wall | obstacle, name)
    layout = Layout(name, wall, obstacle, agent_start, victim_pos, region, names, kinds,
                    rubble=chars == "r", roles=(chars[tuple(agent_start.T)] == "E").astype(np.int32),
                    victim_kind=(chars[tuple(victim_pos.T)] == "C").astype(np.int32),
                    random_cells=np.argwhere(chars == "?").astype(np.int32), header=header)
    check_victims(layout, header.get("random_victims", HEADER_KEYS["random_victims"]))
    _check_reachable(layout)
    return layout


def check_victims(layout: Layout, random_victims: tuple[int, int]) -> None:
    """The victims a map gets with ``random_victims`` drawn over its '?' cells can exist and be triaged."""
    where, drawn, cells = f"layout {layout.name!r}", sum(random_victims), len(layout.random_cells)
    if cells and not drawn:
        raise LayoutError(f"{where}: {cells} '?' cells but no victims drawn on them; set the header line "
                          "'random_victims: N_REGULAR N_CRITICAL' (or turn the '?' cells into '.')")
    if drawn > cells:
        raise LayoutError(f"{where}: random_victims={tuple(random_victims)} draws {drawn} victims but the map has "
                          f"only {cells} '?' cells to draw them on")
    if len(layout.victim_pos) + drawn == 0:
        raise LayoutError(f"{where}: no victim ('V' regular, 'C' critical, or random_victims over '?' cells)")
    if not np.any(layout.roles == MEDIC):
        raise LayoutError(f"{where}: victims but no medic ('A') to triage them (engineers 'E' only clear rubble)")


def _neighbours(mask: np.ndarray) -> np.ndarray:
    """bool[H, W]: cells 4-adjacent to some cell of ``mask``."""
    near = np.zeros_like(mask)
    near[1:] |= mask[:-1]
    near[:-1] |= mask[1:]
    near[:, 1:] |= mask[:, :-1]
    near[:, :-1] |= mask[:, 1:]
    return near


def _check_reachable(layout: Layout) -> None:
    """Every victim (and every '?' cell a victim may be drawn on) must be triageable: a medic can reach a
    cell next to it, ignoring other agents, through rubble only where engineers can clear it first
    (an engineer clears rubble next to a cell it can reach, which may open more rubble to it)."""
    solid = layout.blocked.copy()
    solid[tuple(layout.victim_pos.T)] = True
    starts = lambda role: [tuple(int(x) for x in cell) for cell in layout.agent_start[layout.roles == role]]
    reach = lambda open_, role: _geodesic(open_, starts(role))[0] >= 0
    cleared = np.zeros_like(layout.rubble)
    while True:  # rubble the engineers can clear, in waves
        reachable = _neighbours(reach(~solid & ~(layout.rubble & ~cleared), ENGINEER))
        newly = layout.rubble & ~cleared & reachable
        if not newly.any():
            break
        cleared |= newly
    medics = _neighbours(reach(~solid & ~(layout.rubble & ~cleared), MEDIC))
    medics_all_clear = _neighbours(reach(~solid, MEDIC))
    targets = [(f"victim {v}", cell) for v, cell in enumerate(layout.victim_pos)]
    if layout.header.get("random_victims", (0, 0)) != (0, 0):
        targets += [("'?' cell", cell) for cell in layout.random_cells]
    for what, (r, c) in targets:
        if not medics_all_clear[r, c]:
            raise LayoutError(f"layout {layout.name!r}: {what} at ({r}, {c}) cannot be reached by any medic, "
                              "even with every rubble cleared")
        if not medics[r, c]:
            why = ("no engineer can reach the rubble in the way" if np.any(layout.roles == ENGINEER)
                   else "the map has no engineer ('E') to clear it")
            raise LayoutError(f"layout {layout.name!r}: {what} at ({r}, {c}) is behind rubble and {why}")


def _parse_regions(text, shape, blocked, name):
    what = f"region grid of {name!r}"
    header, grid = _split_header(text, what)
    letters, names, kinds = [], [], []
    for line in header:
        parts = line.split()
        if len(parts) != 3 or len(parts[0]) != 1:
            raise LayoutError(f"{what}: legend line {line!r} is not 'letter name kind'")
        letter, rname, kind = parts
        if letter in ("#", ".") or letter in letters:
            raise LayoutError(f"{what}: legend letter {letter!r} is reserved or repeated")
        if kind not in REGION_KINDS:
            raise LayoutError(f"{what}: region {rname!r} has kind {kind!r}; expected one of {REGION_KINDS}")
        letters.append(letter), names.append(rname), kinds.append(kind)
    if not letters:
        raise LayoutError(f"{what}: no legend lines ('letter name kind') before '---'")
    cells = np.array([list(row) for row in grid])
    if cells.shape != shape:
        raise LayoutError(f"{what}: grid is {cells.shape[0]}x{cells.shape[1]} but the layout is {shape[0]}x{shape[1]}")
    mismatch = np.argwhere((cells == "#") != blocked)
    if len(mismatch):
        r, c = mismatch[0]
        want = "'#' (wall or obstacle)" if blocked[r, c] else "a region letter (open cell)"
        raise LayoutError(f"{what}: cell ({r}, {c}) is {str(cells[r, c])!r} but the layout needs {want} there")
    unknown = sorted(map(str, set(cells[~blocked].ravel()) - set(letters)))
    if unknown:
        r, c = np.argwhere(cells == unknown[0])[0]
        raise LayoutError(f"{what}: letter {unknown[0]!r} at ({r}, {c}) is not in the legend {letters}")
    region = np.full(shape, -1, dtype=np.int32)
    for i, letter in enumerate(letters):
        region[cells == letter] = i
    return region, tuple(names), tuple(kinds)


def _geodesic(mask: np.ndarray, seeds) -> tuple[np.ndarray, np.ndarray]:
    """Breadth-first steps within ``mask`` from the nearest of ``seeds`` ((row, col) cells) and which seed
    that is (the first seed wins a tie): (dist, owner) int32[H, W], -1 where no seed reaches."""
    h, w = mask.shape
    dist, owner = np.full((h, w), -1, np.int32), np.full((h, w), -1, np.int32)
    frontier = []
    for k, (r, c) in enumerate(seeds):
        dist[r, c], owner[r, c] = 0, k
        frontier.append((r, c))
    while frontier:
        nxt = []
        for r, c in frontier:
            for nr, nc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
                if 0 <= nr < h and 0 <= nc < w and mask[nr, nc] and dist[nr, nc] < 0:
                    dist[nr, nc], owner[nr, nc] = dist[r, c] + 1, owner[r, c]
                    nxt.append((nr, nc))
        frontier = nxt
    return dist, owner


def available_layouts() -> list[str]:
    return sorted(p.name[: -len(".txt")] for p in LAYOUT_DIR.glob("*.txt") if not p.name.endswith(".regions.txt"))


def layout_path(name: str) -> Path:
    """The ``.txt`` file of a shipped map name (``two_rooms``) or of a path to a layout."""
    path = Path(name)
    if path.suffix == ".txt" and path.exists():
        return path
    if (LAYOUT_DIR / f"{name}.txt").exists():
        return LAYOUT_DIR / f"{name}.txt"
    raise LayoutError(f"unknown map {name!r}; available: {', '.join(available_layouts())} (or a path to a .txt layout)")


def companion(path: Path, suffix: str) -> Path:
    """``NAME.txt`` -> ``NAME<suffix>`` beside it (``.regions.txt``, ``.settings.yaml``)."""
    return path.with_name(path.name[: -len(".txt")] + suffix)


def load_layout(name: str) -> Layout:
    """Load a shipped layout by name (``two_rooms``) or from a path to a ``.txt`` layout file."""
    path = layout_path(name)
    regions_path = companion(path, ".regions.txt")
    text = path.read_text()
    if regions_path.exists():  # a hand-made (or edited) region grid wins
        return parse_layout(text, regions_path.read_text(), name=path.stem)
    from jaxusar.envs.mapgen import segmented_regions_text

    regions = segmented_regions_text(text, path.stem)
    layout = parse_layout(text, regions, name=path.stem)  # a bad layout fails here, before anything is written
    try:
        regions_path.write_text(regions)
        warnings.warn(f"map {name!r} had no region grid: segmented it from the layout into "
                      f"{', '.join(f'{n} ({k})' for n, k in zip(layout.region_names, layout.region_kinds))} "
                      f"and wrote {regions_path} (edit it to change the regions)", stacklevel=2)
    except OSError as err:
        warnings.warn(f"map {name!r} had no region grid: segmented it from the layout, but could not write "
                      f"{regions_path} ({err.strerror or err})", stacklevel=2)
    return layout


def settings_path(name: str) -> Path | None:
    """The map's own config settings (``NAME.settings.yaml`` beside its layout), if it has one.

    They hold what only makes sense on that map, such as a discount for one of its named tasks, and
    apply to every run on it (``jaxusar.config.load``). None for an unknown map (its error comes from
    the env)."""
    try:
        path = companion(layout_path(name), ".settings.yaml")
    except LayoutError:
        return None
    return path if path.exists() else None
