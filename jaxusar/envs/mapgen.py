"""Maps without hand work: region grids segmented from a layout, and a seeded rooms-and-corridors generator.

``segment(blocked)``: rooms are the open areas wide enough to hold a 3x3 block of open cells; what is
left (corridors, and the doorways in room walls) is hall. Doorways thus split regions: a 1-wide gap in
a wall belongs to the corridor it opens onto, and the room behind it starts at its first wide cell.
Small thin pockets (an alcove of a room, a doorway directly between two rooms) join a room they touch.
A long hall is cut into pieces (``HALL_RADIUS``), so that navigating to a region never means crossing a
whole corridor.
A hand-made ``NAME.regions.txt`` always wins; ``layout.load_layout`` segments only a map without one,
and writes the result beside it for a person to inspect and edit.

``generate(height, width, rooms, medics, victims, seed)``: rows of rooms along 1-wide horizontal
corridors (a corridor between two rows of rooms, each room with one doorway onto it), joined by a
vertical corridor down the left edge. Medics start in corridors, victims lie in distinct rooms while
rooms last. Contract part 2's features are keyword arguments (all off by default, and drawn from the
seed's generator after everything above, so a map without them is the same as before they existed):
engineers start in corridors, ``rubble`` doorways are blocked by rubble, ``critical`` of the fixed
victims are critical, and ``random_regular`` + ``random_critical`` victims are drawn at reset over up to
``draw_cells`` '?' cells per room (the header line ``random_victims``); ``settings`` adds header lines
(``triage_steps``, ``critical_expires``, ``view_radius``, ...). Pure numpy: the same arguments give the
same map on every machine, and the map is checked solvable (every victim and '?' cell reachable by some
medic, past rubble the engineers can clear) by the same parser that loads shipped maps.
"""

from __future__ import annotations

import string

import numpy as np

from jaxusar.envs.layout import HEADER_KEYS, Layout, LayoutError, _geodesic, _neighbours, header_value, parse_layout

LETTERS = string.ascii_uppercase + string.ascii_lowercase + string.digits
WIDE = 3         # a room holds a WIDE x WIDE block of open cells; a narrower area is hall
POCKET = 4       # a thin area of at most this many cells touching a room joins it
HALL_RADIUS = 4  # halls are cut into pieces within this many steps of a piece's centre (0: kept whole)


def _components(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """4-connected components of ``mask``: (labels int32[H, W], -1 outside; count), in row-major order."""
    h, w = mask.shape
    labels = np.full((h, w), -1, np.int32)
    n = 0
    for r0, c0 in zip(*np.nonzero(mask)):
        if labels[r0, c0] >= 0:
            continue
        labels[r0, c0] = n
        stack = [(r0, c0)]
        while stack:
            r, c = stack.pop()
            for nr, nc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
                if 0 <= nr < h and 0 <= nc < w and mask[nr, nc] and labels[nr, nc] < 0:
                    labels[nr, nc] = n
                    stack.append((nr, nc))
        n += 1
    return labels, n


def _wide(open_: np.ndarray) -> np.ndarray:
    """bool[H, W]: open cells inside some WIDE x WIDE block of open cells (a morphological opening)."""
    h, w = open_.shape
    fits = np.ones((max(h - WIDE + 1, 0), max(w - WIDE + 1, 0)), bool)
    for dr in range(WIDE):
        for dc in range(WIDE):
            fits &= open_[dr:dr + fits.shape[0], dc:dc + fits.shape[1]]
    wide = np.zeros_like(open_)
    for dr in range(WIDE):
        for dc in range(WIDE):
            wide[dr:dr + fits.shape[0], dc:dc + fits.shape[1]] |= fits
    return wide


def _touching(labels: np.ndarray, mask: np.ndarray) -> set[int]:
    """Labels of the cells 4-adjacent to ``mask``."""
    return set(int(x) for x in np.unique(labels[_neighbours(mask) & ~mask]) if x >= 0)


def _pieces(cells: np.ndarray, radius: int) -> list[np.ndarray]:
    """A connected hall ``cells`` (bool[H, W]) cut into pieces whose every cell lies within ``radius``
    steps of its piece's seed: seeds by farthest-point sampling from the hall's first cell (row-major),
    each cell to its nearest seed. One piece when the hall is that small already."""
    seeds = [tuple(int(x) for x in np.argwhere(cells)[0])]
    while True:
        dist, owner = _geodesic(cells, seeds)
        far = np.unravel_index(np.argmax(dist), dist.shape)
        if dist[far] <= radius:
            return [owner == k for k in range(len(seeds))]
        seeds.append(tuple(int(x) for x in far))


def segment(blocked: np.ndarray, hall_radius: int = HALL_RADIUS) -> tuple[np.ndarray, tuple[str, ...], tuple[str, ...]]:
    """Rooms and halls of a map from its blocked cells alone.

    ``hall_radius`` > 0 cuts every hall into pieces of at most that many steps from a piece's centre,
    so that no navigation sub-task (to a region from the regions next to it) has to cross a long
    corridor: chained navigation then goes along a corridor piece by piece (measured on office:
    benchmarks/README.md, "Long corridors cut into pieces"); 0 keeps each hall whole. Where the pieces
    would be more regions than a region file holds, the radius doubles until they fit (the written
    region file's header says which radius).

    Returns (region int32[H, W] with -1 on blocked cells, names, kinds), regions numbered rooms first
    in row-major order of their first cell (``room_0``, ``room_1``, ..., then ``hall_0``, ...).
    """
    return _segment(blocked, hall_radius)[:3]


def _segment(blocked, hall_radius):
    """``segment``'s three outputs and the radius it cut halls at."""
    open_ = ~np.asarray(blocked, bool)
    rooms, n_rooms = _components(_wide(open_))
    thin, n_thin = _components(open_ & (rooms < 0))
    region = rooms.copy()
    whole = []
    for t in range(n_thin):
        cells = thin == t
        near = sorted(_touching(rooms, cells))
        if near and cells.sum() <= POCKET and (len(near) == 1 or cells.sum() <= 2):
            region[cells] = near[0]  # an alcove, or a doorway straight from one room into another
        else:
            whole.append(cells)
    radius = hall_radius
    while True:
        halls = [p for cells in whole for p in (_pieces(cells, radius) if radius > 0 else [cells])]
        if n_rooms + len(halls) <= len(LETTERS) or len(halls) == len(whole):
            break
        radius *= 2
    for k, cells in enumerate(halls):
        region[cells] = n_rooms + k
    names = tuple(f"room_{i}" for i in range(n_rooms)) + tuple(f"hall_{k}" for k in range(len(halls)))
    if len(names) > len(LETTERS):
        raise LayoutError(f"segmentation found {len(names)} regions; a region file holds at most {len(LETTERS)}")
    return region, names, ("room",) * n_rooms + ("hall",) * len(halls), radius


def regions_text(region: np.ndarray, names, kinds, comment: str = "") -> str:
    """A region grid file (``NAME.regions.txt``) for ``region``: legend lines, ``---``, one letter per cell."""
    head = [f"; {line}" for line in comment.splitlines()] if comment else []
    legend = [f"{LETTERS[i]} {name} {kind}" for i, (name, kind) in enumerate(zip(names, kinds))]
    grid = ["".join("#" if x < 0 else LETTERS[x] for x in row) for row in region]
    return "\n".join(head + legend + ["---"] + grid) + "\n"


# -- the generator -----------------------------------------------------------------------------------
class GeneratorError(ValueError):
    """Generator arguments that cannot make a map (too small, too many rooms, ...)."""


def _split(total: int, parts: int, least: int, rng: np.random.Generator) -> list[int]:
    """``parts`` sizes >= ``least`` summing to ``total``, the slack spread at random."""
    sizes = np.full(parts, least)
    for i in rng.integers(0, parts, total - least * parts):
        sizes[i] += 1
    return sizes.tolist()


def _overhead(n_rows: int) -> int:
    """Rows of wall and corridor around ``n_rows`` room rows: an even row is followed by a wall (its
    doorways) and a corridor, and after the first is preceded by a wall; an odd row sits behind a wall
    (its doorways) below the corridor before it."""
    return sum(2 + (i > 0) if i % 2 == 0 else 1 for i in range(n_rows))


def _per_row(width: int) -> int:
    return (width - 1) // (WIDE + 1)  # rooms in cols 2..width-1 with a wall between two; col 0 corridor


def room_capacity(height: int, width: int) -> int:
    """The most rooms ``generate`` fits in a height x width map (rooms at least WIDE x WIDE)."""
    rows = 0
    while _overhead(rows + 1) + WIDE * (rows + 1) <= height:
        rows += 1
    return _per_row(width) * rows


DRAW_CELLS = 3  # '?' cells per room (at most) where victims are drawn at reset, by default
FEATURES = {"engineers": 0, "rubble": 0, "critical": 0, "random_regular": 0, "random_critical": 0,
            "draw_cells": DRAW_CELLS}  # generate's part-2 arguments and their defaults (all features off)
SETTINGS = tuple(k for k in HEADER_KEYS if k != "random_victims")  # header lines ``settings`` may add


def _count(name: str, value, least: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
        raise GeneratorError(f"{name}={value!r}: must be an integer >= {least}")
    return int(value)


def _check_features(rooms: int, victims: int, engineers: int, rubble: int, critical: int, random_regular: int,
                    random_critical: int, draw_cells: int, settings: dict | None) -> list[str]:
    """Check the part-2 arguments against each other; returns the header's ``key: value`` lines."""
    for name, value, least in (("engineers", engineers, 0), ("rubble", rubble, 0), ("critical", critical, 0),
                               ("random_regular", random_regular, 0), ("random_critical", random_critical, 0),
                               ("draw_cells", draw_cells, 1)):
        _count(name, value, least)
    drawn = random_regular + random_critical
    if rubble and not engineers:
        raise GeneratorError(f"rubble={rubble} needs engineers >= 1 to clear it (no medic can)")
    if rubble > rooms:
        raise GeneratorError(f"rubble={rubble}: only {rooms} doorways (one per room) to put rubble in")
    if critical > victims:
        raise GeneratorError(f"critical={critical}: more than the {victims} fixed victims")
    lines = [f"random_victims: {random_regular} {random_critical}"] if drawn else []
    for key, value in (settings or {}).items():
        if key not in SETTINGS:
            raise GeneratorError(f"setting {key!r}: unknown; known: {', '.join(SETTINGS)} (random_victims comes from "
                                 "random_regular and random_critical)")
        try:
            value = header_value(key, value, "map setting")
        except LayoutError as err:
            raise GeneratorError(str(err)) from None
        if value is not None:
            lines.append(f"{key}: {value}")
    return sorted(lines, key=lambda line: list(HEADER_KEYS).index(line.split(":")[0]))


def _clear_around(grid: np.ndarray, room: tuple[int, int, int, int], cell: tuple[int, int]) -> bool:
    """Whether ``cell`` and its 8 neighbours are floor inside ``room`` (top, left, height, width): a victim
    drawn there never walls anything in, whichever other such cells hold one."""
    top, left, h, w = room
    r, c = cell
    return top < r < top + h - 1 and left < c < left + w - 1 and bool(np.all(grid[r - 1:r + 2, c - 1:c + 2] == "."))


def _add_features(grid: np.ndarray, rng: np.random.Generator, hall, doors, rooms, engineers: int, rubble: int,
                  critical: int, drawn: int, draw_cells: int) -> None:
    """Contract part 2's features, drawn from ``rng`` after the part-1 map (in place): engineers in corridor
    cells, rubble in doorways, critical fixed victims, and '?' cells in rooms."""
    if engineers:
        free = [cell for cell in hall if grid[cell] == "."]
        if engineers > len(free):
            raise GeneratorError(f"{engineers} engineers do not fit in the {len(free)} free corridor cells of this map")
        for k in sorted(rng.choice(len(free), engineers, replace=False)):
            grid[free[k]] = "E"
    if rubble:
        for k in sorted(rng.choice(len(doors), rubble, replace=False)):
            grid[doors[k]] = "r"
    if critical:
        fixed = [tuple(int(x) for x in cell) for cell in np.argwhere(grid == "V")]
        for k in sorted(rng.choice(len(fixed), critical, replace=False)):
            grid[fixed[k]] = "C"
    if drawn:
        cells = 0
        for room in rooms:
            top, left, h, w = room
            candidates = [(r, c) for r in range(top, top + h) for c in range(left, left + w)
                          if _clear_around(grid, room, (r, c))]
            placed = 0
            for k in rng.permutation(len(candidates)):
                if placed == draw_cells:
                    break
                if _clear_around(grid, room, candidates[k]):  # still clear of the '?' cells placed so far
                    grid[candidates[k]] = "?"
                    placed += 1
            cells += placed
        if cells < drawn:
            raise GeneratorError(f"{drawn} victims drawn at reset need as many '?' cells; the rooms of this map hold "
                                 f"{cells} (at most {draw_cells} per room, each with floor on all 8 sides); ask for "
                                 "more draw_cells, bigger rooms or fewer drawn victims")


def generate(height: int, width: int, rooms: int, medics: int, victims: int, seed: int = 0, *,
             engineers: int = 0, rubble: int = 0, critical: int = 0, random_regular: int = 0, random_critical: int = 0,
             draw_cells: int = DRAW_CELLS, settings: dict | None = None) -> str:
    """A rooms-and-corridors layout (the ``.txt`` text, header included), the same for the same arguments.

    Part 2 (DESIGN.md): ``engineers`` start in corridors; ``rubble`` of the rooms' doorways hold rubble
    (needs an engineer); ``critical`` of the ``victims`` are critical ('C'); ``random_regular`` and
    ``random_critical`` victims are drawn at reset over up to ``draw_cells`` '?' cells per room (each with
    floor on all 8 sides, so no draw walls anything in); ``settings`` {key: value} adds header lines
    (``SETTINGS``: triage_steps, critical_triage_steps, critical_reward, critical_expires, view_radius,
    observation). Not checked here; ``generated_layout`` parses it (every victim reachable) and segments
    its regions."""
    for name, value, least in (("height", height, 2 * WIDE), ("width", width, WIDE + 2), ("rooms", rooms, 1),
                               ("medics", medics, 1), ("victims", victims, 0), ("seed", seed, 0)):
        _count(name, value, least)
    drawn = _count("random_regular", random_regular, 0) + _count("random_critical", random_critical, 0)
    if victims < 1 and not drawn:
        raise GeneratorError(f"victims={victims!r}: a map needs a victim (victims >= 1, or some drawn at reset: "
                             "random_regular, random_critical)")
    header_lines = _check_features(rooms, victims, engineers, rubble, critical, random_regular, random_critical,
                                   draw_cells, settings)
    capacity = room_capacity(height, width)
    if rooms > capacity:
        raise GeneratorError(f"{rooms} rooms do not fit in a {height}x{width} map (at most {capacity} rooms of "
                             f"{WIDE}x{WIDE} cells or more); ask for fewer rooms or a bigger map")
    rng = np.random.default_rng(seed)
    fits = [r for r in range(1, rooms + 1) if _overhead(r) + WIDE * r <= height and r * _per_row(width) >= rooms]
    aspect = lambda r: abs(np.log((height - _overhead(r)) / r) - np.log((width - 2) / -(-rooms // r)))
    n_rows = min(fits, key=aspect)  # rooms as near square as the map allows
    counts = [rooms // n_rows + (i < rooms % n_rows) for i in range(n_rows)]
    heights = _split(height - _overhead(n_rows), n_rows, WIDE, rng)
    grid = np.full((height, width), "#", dtype="<U1")
    grid[:, 0] = "."  # the vertical corridor down the left edge
    corridors, room_cells, inside_door, doors, room_boxes = [], [], set(), [], []
    r = 0
    for i in range(n_rows):
        if i % 2 == 0:
            r += i > 0  # the wall after the previous pair of rows
            top = r
            door_row, r = top + heights[i], top + heights[i] + 2
            corridors.append(door_row + 1)
            grid[door_row + 1, :] = "."
        else:
            door_row = r
            top = r = r + 1
            r += heights[i]
        widths = _split(width - 2 - (counts[i] - 1), counts[i], WIDE, rng)
        c = 2
        for wd in widths:
            grid[top:top + heights[i], c:c + wd] = "."
            door_col = int(rng.integers(c, c + wd))
            grid[door_row, door_col] = "."
            doors.append((door_row, door_col))
            inside_door.add((door_row - 1 if i % 2 == 0 else door_row + 1, door_col))
            room_cells.append([(rr, cc) for rr in range(top, top + heights[i]) for cc in range(c, c + wd)])
            room_boxes.append((top, c, heights[i], wd))
            c += wd + 1
    grid[corridors[-1] + 1:, 0] = "#"  # the vertical corridor ends at the last corridor
    hall = [(rr, 0) for rr in range(corridors[-1] + 1)] + [(cr, cc) for cr in corridors for cc in range(1, width)]
    if medics > len(hall):
        raise GeneratorError(f"{medics} medics do not fit in the {len(hall)} corridor cells of this map")
    for k in sorted(rng.choice(len(hall), medics, replace=False)):
        grid[hall[k]] = "A"
    order = rng.permutation(len(room_cells))
    for j in range(victims):
        free = [cell for cell in room_cells[order[j % len(room_cells)]] if grid[cell] == "." and cell not in inside_door]
        if not free:
            raise GeneratorError(f"{victims} victims do not fit in the rooms of this map")
        grid[free[int(rng.integers(len(free)))]] = "V"
    _add_features(grid, rng, hall, doors, room_boxes, engineers, rubble, critical, drawn, draw_cells)
    features = dict(engineers=engineers, rubble=rubble, critical=critical, random_regular=random_regular,
                    random_critical=random_critical, draw_cells=draw_cells)
    given = "".join(f", {k}={v}" for k, v in features.items() if v != FEATURES[k] and (k != "draw_cells" or drawn))
    given += f", settings={dict(settings)!r}" if settings else ""
    header = (f"; generated by jaxusar.envs.mapgen.generate(height={height}, width={width}, rooms={rooms}, "
              f"medics={medics}, victims={victims}, seed={seed}{given})\n"
              + "".join(f"{line}\n" for line in header_lines) + "---\n")
    return header + "\n".join("".join(row) for row in grid) + "\n"


def generated_layout(height: int, width: int, rooms: int, medics: int, victims: int, seed: int = 0,
                     name: str = "generated", hall_radius: int = HALL_RADIUS, **features) -> tuple[Layout, str, str]:
    """``generate`` parsed and checked: (Layout, layout text, region grid text). ``features``: ``generate``'s
    keyword arguments (engineers, rubble, critical, random_regular, random_critical, draw_cells, settings)."""
    text = generate(height, width, rooms, medics, victims, seed, **features)
    regions = segmented_regions_text(text, name, hall_radius)
    try:
        return parse_layout(text, regions, name=name), text, regions
    except LayoutError as err:  # e.g. victims sharing a small room wall one another in
        raise GeneratorError(f"seed {seed} made an unsolvable map ({err}); try another seed or fewer victims") from None


def segmented_regions_text(layout_text: str, name: str = "<string>", hall_radius: int = HALL_RADIUS) -> str:
    """The region grid file ``segment`` makes for a layout's text."""
    from jaxusar.envs.layout import _split_header

    _, rows = _split_header(layout_text, f"layout {name!r}")
    chars = np.array([list(row) for row in rows])
    region, names, kinds, radius = _segment((chars == "#") | (chars == "X"), hall_radius)
    return regions_text(region, names, kinds, f"region grid of {name!r} segmented from its layout "
                        f"(jaxusar.envs.mapgen.segment, hall_radius={radius}); edit freely: a region file "
                        "beside a layout wins")
