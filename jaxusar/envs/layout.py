"""ASCII layouts and region grids -> static numpy arrays (validated once, outside jit).

A map is two text files in ``jaxusar/envs/layouts/``:

``NAME.txt``          the layout. Legend: ``#`` wall, ``X`` obstacle, ``.`` floor, ``V`` victim,
                      ``A`` agent start. Agents and victims are numbered in row-major reading order.
``NAME.regions.txt``  the region grid (the paper's graph view, Fig. 3): one letter per cell, ``#``
                      exactly on the wall and obstacle cells; its header names each letter
                      (``T top_room room``; the kind is ``room`` or ``hall``). A map without one is
                      segmented from its layout (``mapgen.segment``: rooms are the areas wide enough
                      for 3x3 open cells, corridors and doorways are hall), and the grid is written
                      beside it to inspect and edit.
``NAME.settings.yaml`` optional: config settings that belong to this map (they name its tasks), merged
                      over an algorithm's defaults in every run on it (``jaxusar.config.load``).

Each file may start with a header that ends at a line ``---``; header lines starting with ``;``
are comments. A file without ``---`` is all grid.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np

LAYOUT_DIR = Path(__file__).parent / "layouts"
LAYOUT_CHARS = {"#": "wall", "X": "obstacle", ".": "floor", "V": "victim", "A": "agent start"}
REGION_KINDS = ("room", "hall")


class LayoutError(ValueError):
    """A layout or region grid that cannot describe a valid map."""


@dataclasses.dataclass(frozen=True, eq=False)
class Layout:
    """A parsed, validated map. All arrays are numpy (static: closed over by the jitted env).

    Attributes:
      name:          the map's name.
      wall:          bool[H, W], wall cells.
      obstacle:      bool[H, W], obstacle cells.
      agent_start:   int32[n_agents, 2], (row, col) of each agent's start, row-major order.
      victim_pos:    int32[n_victims, 2], (row, col) of each victim, row-major order.
      region:        int32[H, W], region index of each cell, -1 on wall and obstacle cells.
      region_names:  tuple[str], one per region, in order of first appearance in the header.
      region_kinds:  tuple[str], ``room`` or ``hall`` per region.
    """

    name: str
    wall: np.ndarray
    obstacle: np.ndarray
    agent_start: np.ndarray
    victim_pos: np.ndarray
    region: np.ndarray
    region_names: tuple[str, ...]
    region_kinds: tuple[str, ...]

    @property
    def shape(self) -> tuple[int, int]:
        return self.wall.shape

    @property
    def blocked(self) -> np.ndarray:
        return self.wall | self.obstacle

    def to_ascii(self) -> str:
        """The layout as the ASCII grid it was parsed from."""
        grid = np.full(self.shape, ".", dtype="<U1")
        grid[self.wall] = "#"
        grid[self.obstacle] = "X"
        for r, c in self.victim_pos:
            grid[r, c] = "V"
        for r, c in self.agent_start:
            grid[r, c] = "A"
        return "\n".join("".join(row) for row in grid)

    def subset(self, agents=None, victims=None) -> "Layout":
        """The same map with only the given agents and victims (by index; order kept).

        Used for the paper's sub-tasks, where "the other agents and victims are removed" (Sec. IV-B).
        """
        agents = range(len(self.agent_start)) if agents is None else list(agents)
        victims = range(len(self.victim_pos)) if victims is None else list(victims)
        return dataclasses.replace(
            self,
            agent_start=self.agent_start[list(agents)].reshape(-1, 2),
            victim_pos=self.victim_pos[list(victims)].reshape(-1, 2),
        )


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
    _, grid = _split_header(text, f"layout {name!r}")
    chars = np.array([list(row) for row in grid])
    unknown = sorted(map(str, set(chars.ravel()) - set(LAYOUT_CHARS)))  # str: np.str_ reprs as np.str_(...)
    if unknown:
        r, c = np.argwhere(chars == unknown[0])[0]
        raise LayoutError(
            f"layout {name!r}: unknown character {unknown[0]!r} at row {r}, col {c}; "
            f"legend: " + ", ".join(f"{k!r} {v}" for k, v in LAYOUT_CHARS.items())
        )
    wall, obstacle = chars == "#", chars == "X"
    agent_start = np.argwhere(chars == "A").astype(np.int32)
    victim_pos = np.argwhere(chars == "V").astype(np.int32)  # argwhere is row-major order
    if len(agent_start) == 0:
        raise LayoutError(f"layout {name!r}: no agent start ('A')")
    if len(victim_pos) == 0:
        raise LayoutError(f"layout {name!r}: no victim ('V')")

    region, names, kinds = _parse_regions(regions_text, chars.shape, wall | obstacle, name)
    layout = Layout(name, wall, obstacle, agent_start, victim_pos, region, names, kinds)
    _check_reachable(layout)
    return layout


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


def _check_reachable(layout: Layout) -> None:
    """Every victim must be triageable: some agent can reach a cell next to it (ignoring other agents)."""
    h, w = layout.shape
    solid = layout.blocked.copy()
    solid[tuple(layout.victim_pos.T)] = True
    seen = _geodesic(~solid, [tuple(int(x) for x in cell) for cell in layout.agent_start])[0] >= 0
    for v, (r, c) in enumerate(layout.victim_pos):
        near = [(r + dr, c + dc) for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0))]
        if not any(0 <= nr < h and 0 <= nc < w and seen[nr, nc] for nr, nc in near):
            raise LayoutError(f"layout {layout.name!r}: victim {v} at ({r}, {c}) cannot be reached by any agent")


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
