"""Pictures of USAR states: ASCII for terminals and tests, matplotlib in the paper's Fig. 2 colours.

Side effects (files, figures) live here and in the CLI only; nothing here is called inside ``jit``.
Every function takes one unbatched ``EnvState`` (or a list of them); jax arrays are read with numpy.
Victims are drawn where the state puts them (``state.victim_pos``: drawn at reset on maps with '?' cells).

ASCII legend (``render_ascii``; ``ascii_legend(env)`` names the characters a map uses):

  ``#`` wall, ``X`` obstacle, ``.`` floor, ``r`` rubble, ``,`` rubble cleared (floor now),
  ``V`` untriaged regular victim, ``C`` untriaged critical victim, ``+`` triaged victim, ``x`` dead victim,
  ``> v < ^`` a medic facing east, south, west, north; ``e s w n`` an engineer facing east, south, west, north.
  With ``fog`` (the team's knowledge; on by default for ``observation="view"`` maps): a blank is an open
  cell the team has not seen, ``?`` an unseen cell that may hold a victim (a fixed victim's cell or a '?'
  cell of the layout: where a victim is drawn stays hidden). Walls, obstacles and rubble are known to
  every agent and always shown; agents are always shown.

The last line is ``t=3 triaged=[0 1]``, then ``dead=[...]`` where critical victims expire and
``progress=[...]`` (TRIAGE actions received) where a victim needs more than one. A part-1 map renders
as it always has.

Pictures (``render_state``): each agent in its own colour (agent 0 the paper's blue), a medic a square
and an engineer a disc, with a white arrow for its facing; regular victims green, critical ones red
with a ``!``, triaged ones pale with a check mark, dead ones dark maroon with a cross; rubble brown and
hatched, cleared rubble a few brown pebbles on the floor; with ``fog`` a dark veil over the cells the
team has not seen, and a ``?`` on each of them that may hold a victim.
"""

from __future__ import annotations

import textwrap
from functools import lru_cache
from pathlib import Path

import jax
import numpy as np

from jaxusar.envs.layout import CRITICAL, ENGINEER
from jaxusar.envs.layout import MEDIC as MEDIC_ROLE
from jaxusar.envs.usar import DIR_DELTA, EnvState, USAREnv

ARROWS = ">v<^"  # a medic, by facing: EAST SOUTH WEST NORTH
ENGINEER_ARROWS = "eswn"  # an engineer, by facing: the compass letter
# The paper's Fig. 2 palette, and the part-2 additions.
FLOOR, WALL, OBSTACLE = "#c0c0c0", "#000000", "#2d2d2d"
VICTIM, TRIAGED_VICTIM = "#3f9b35", "#a6d99c"
MEDIC = "#2626ff"  # the paper's medic blue: agent 0's colour
CHECK = "#1d5c17"  # the check mark on a triaged victim
CRITICAL_VICTIM, TRIAGED_CRITICAL, CRITICAL_CHECK = "#d7191c", "#f5b3b3", "#8b0000"
DEAD_VICTIM = "#5a1a1a"
RUBBLE, RUBBLE_LINES = "#9c6b3c", "#5c3a17"
VEIL_ALPHA = 0.55  # black over the cells the team has not seen
GRID = "#d9d9d9"
# one colour per agent (cycled past eight): saturated, none near the victims' green or red or the rubble's brown
AGENT_COLOURS = (MEDIC, "#f57c00", "#9b2fc9", "#0a9bb5", "#e8409a", "#1b2a6b", "#b38f00", "#606060")
# region tints of a map picture: warm and violet pastels, none near the victims' green or the medics' blue
ROOM_TINTS = ("#f4a582", "#d6a5c9", "#f7d08a", "#c7b8e8", "#f2b6b6", "#e8c39e", "#e7a1b0", "#d9c27e")
HALL_TINTS = ("#fff7c2", "#c9e4c5", "#bcd7ea", "#e0e0e0")  # touching hall pieces differ: their cut shows
ROLE_WORDS = {MEDIC_ROLE: "medic", ENGINEER: "engineer"}
FOG_LEGEND = "' ' not seen, '?' not seen, may hold a victim"  # the ASCII of what the team has not seen


def agent_colour(i: int) -> str:
    return AGENT_COLOURS[i % len(AGENT_COLOURS)]


def _numpy_state(env: USAREnv, state: EnvState) -> EnvState:
    if np.ndim(state.agent_pos) != 2:
        raise ValueError(f"expected one unbatched EnvState (agent_pos [n_agents, 2]), got agent_pos "
                         f"of shape {np.shape(state.agent_pos)}; index the batch first")
    return jax.tree.map(np.asarray, env.complete(state))  # a part-1 four-field state gets the rest as at reset


def _fog(env: USAREnv, fog: bool | None) -> bool:
    return env.observation == "view" if fog is None else bool(fog)


def _scene(env: USAREnv, state: EnvState, fog: bool):
    """What a picture shows of ``state`` (numpy): (chars str[H, W] in the ASCII legend, shown {victim: (r, c)},
    unseen bool[H, W] the open cells veiled (all False without fog))."""
    layout = env.layout
    grid = np.full(layout.shape, ".", dtype="<U1")
    grid[layout.wall] = "#"
    grid[layout.obstacle] = "X"
    grid[layout.rubble & ~state.rubble] = ","
    grid[state.rubble] = "r"
    unseen = ~layout.blocked & ~state.seen if fog else np.zeros(layout.shape, bool)
    grid[unseen & (grid == ".")] = " "
    shown = {}
    for v, (r, c) in enumerate(state.victim_pos):
        if unseen[r, c]:
            continue
        grid[r, c] = "x" if state.dead[v] else "+" if state.triaged[v] else "VC"[env.victim_kind[v]]
        shown[v] = (int(r), int(c))
    for r, c in np.concatenate([layout.victim_pos, layout.random_cells]):
        if unseen[r, c]:
            grid[r, c] = "?"
    for (r, c), d, role in zip(state.agent_pos, state.agent_dir, env.roles):
        grid[r, c] = (ENGINEER_ARROWS if role == ENGINEER else ARROWS)[d]
    return grid, shown, unseen


def render_ascii(env: USAREnv, state: EnvState, fog: bool | None = None) -> str:
    """The map as text, in the legend of this module's docstring; last line ``t=3 triaged=[0 1]`` (and
    ``dead=``, ``progress=`` where the map uses them). ``fog`` (default: the map's observation is "view")
    shows only what the team has seen."""
    state = _numpy_state(env, state)
    grid, _, _ = _scene(env, state, _fog(env, fog))
    status = f"t={int(state.t)} triaged={state.triaged.astype(int)}"
    if env.expires:
        status += f" dead={state.dead.astype(int)}"
    if env.multi_step:
        status += f" progress={state.progress}"
    return "\n".join(["".join(row) for row in grid] + [status])


def ascii_legend(env: USAREnv, fog: bool | None = None) -> str:
    """The ASCII characters ``render_ascii`` uses on ``env``'s map, in one line."""
    fog = _fog(env, fog)
    roles = set(env.roles.tolist())
    parts = []
    if MEDIC_ROLE in roles:
        parts.append(f"'{ARROWS}' medic{'s' if (env.roles == MEDIC_ROLE).sum() > 1 else ''} facing E S W N")
    if ENGINEER in roles:
        parts.append(f"'{ENGINEER_ARROWS}' engineer{'s' if (env.roles == ENGINEER).sum() > 1 else ''} facing E S W N")
    kinds = set(env.victim_kind.tolist())
    parts.append("'V' victim" if kinds == {0} else "'V' regular victim" if 0 in kinds else "")
    if CRITICAL in kinds:
        parts.append("'C' critical victim")
    parts.append("'+' triaged")
    if env.expires:
        parts.append("'x' dead")
    if env.has_rubble:
        parts += ["'r' rubble", "',' rubble cleared"]
    parts.append("'#' wall")
    if env.layout.obstacle.any():
        parts.append("'X' obstacle")
    if fog:
        parts.append(FOG_LEGEND)
    return ", ".join(p for p in parts if p)


# -- pictures ------------------------------------------------------------------------------------------------
def _figure(width: float, height: float, rows: int = 1, cols: int = 1):
    """A Figure and its Axes grid, outside pyplot: no global backend, no display, nothing to close."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    return fig, fig.subplots(rows, cols, squeeze=False)


def _map_image(env: USAREnv) -> np.ndarray:
    from matplotlib.colors import to_rgb

    image = np.empty(env.layout.shape + (3,))
    image[:] = to_rgb(FLOOR)
    image[env.layout.wall] = to_rgb(WALL)
    image[env.layout.obstacle] = to_rgb(OBSTACLE)
    return image


def render_state(env: USAREnv, state: EnvState, ax=None, title: str | None = None, trail=None,
                 legend: bool = False, label_size: float = 6, fog: bool | None = None, candidates: bool = False):
    """Draw one state in the colours of the paper's Fig. 2 (module docstring) and return the matplotlib Axes.

    Agents and victims carry their index in the top-left corner (``label_size`` points). ``trail``:
    optional int[T, n_agents, 2] of earlier positions, drawn as a faint path in each agent's colour.
    ``legend``: a key below the map (only what the map uses). ``fog`` (default: the map's observation is
    "view"): veil the cells the team has not seen and hide the victims there. ``candidates``: mark the
    '?' cells of the layout that hold no victim (where victims may be drawn), as on a map picture.
    """
    from matplotlib.patches import Circle, Polygon, Rectangle

    state = _numpy_state(env, state)
    fog = _fog(env, fog)
    grid, shown, unseen = _scene(env, state, fog)
    h, w = env.layout.shape
    if ax is None:  # with a legend, wide enough for it even on a small map
        width = max(0.45 * w + 0.4, 7.5 if legend else 0)
        scale = _font_scale(width)
        rows = _legend_rows(_legend_entries(env, fog=fog, candidates=candidates), width, 8 * scale) if legend else 0
        ax = _figure(width, 0.45 * h + 0.6 + 0.28 * scale * rows)[1][0, 0]
    scale = _font_scale(ax.figure.get_figwidth())
    ax.imshow(_map_image(env), interpolation="nearest", origin="upper")
    ax.set_xticks(np.arange(-0.5, w, 1), minor=True)
    ax.set_yticks(np.arange(-0.5, h, 1), minor=True)
    ax.grid(which="minor", color=GRID, linewidth=0.6)
    ax.tick_params(which="both", length=0, labelbottom=False, labelleft=False)
    for spine in ax.spines.values():
        spine.set_color("#808080")

    for r, c in np.argwhere(grid == "r"):
        ax.add_patch(Rectangle((c - 0.5, r - 0.5), 1, 1, facecolor=RUBBLE, edgecolor=RUBBLE_LINES, hatch="////",
                               linewidth=0, zorder=2))
    for r, c in np.argwhere(grid == ","):  # a few pebbles left where rubble was cleared
        ax.scatter(c + np.array([-0.22, 0.18, -0.02]), r + np.array([0.2, 0.12, -0.2]), s=9 * label_size / 6,
                   color=RUBBLE, zorder=2, linewidths=0)
    if candidates:
        for r, c in env.layout.random_cells:
            if grid[r, c] == ".":
                ax.text(c, r, "?", ha="center", va="center", color="#6a6a6a", fontsize=label_size * 1.4, zorder=2)

    if trail is not None:
        trail = np.asarray(trail).reshape(-1, env.n_agents, 2)
        for i in range(env.n_agents):
            path = np.concatenate([trail[:, i], state.agent_pos[None, i]])
            ax.plot(path[:, 1], path[:, 0], color=agent_colour(i), alpha=0.4, linewidth=2.5, zorder=2,
                    solid_capstyle="round", solid_joinstyle="round")

    for v, (r, c) in shown.items():
        critical = env.victim_kind[v] == CRITICAL
        mark = grid[r, c]
        if mark == "x":
            color, label_color = DEAD_VICTIM, "white"
        elif mark == "+":
            color, label_color = (TRIAGED_CRITICAL, CRITICAL_CHECK) if critical else (TRIAGED_VICTIM, CHECK)
        else:
            color, label_color = (CRITICAL_VICTIM if critical else VICTIM), "white"
        ax.add_patch(Rectangle((c - 0.5, r - 0.5), 1, 1, color=color, zorder=3))
        if mark == "+":  # a check mark as well as the paler colour, so triage reads without colour vision
            ax.plot([c - 0.28, c - 0.06, c + 0.3], [r + 0.02, r + 0.25, r - 0.25], color=label_color,
                    linewidth=2.5, solid_capstyle="round", zorder=4)
        elif mark == "x":
            ax.plot([c - 0.25, c + 0.25], [r - 0.2, r + 0.3], color="white", linewidth=2, zorder=4)
            ax.plot([c - 0.25, c + 0.25], [r + 0.3, r - 0.2], color="white", linewidth=2, zorder=4)
        else:
            if critical:
                ax.text(c + 0.05, r + 0.05, "!", ha="center", va="center", color="white", fontweight="bold",
                        fontsize=label_size * 1.8, zorder=4)
            needed, done = int(env.needed[v]), int(state.progress[v])
            if needed > 1 and done > 0:  # TRIAGE actions received so far: a bar along the bottom
                ax.add_patch(Rectangle((c - 0.4, r + 0.3), 0.8, 0.13, facecolor="none", edgecolor="white",
                                       linewidth=0.8, zorder=4))
                ax.add_patch(Rectangle((c - 0.4, r + 0.3), 0.8 * done / needed, 0.13, color="white", zorder=4))
        _corner_label(ax, r, c, v, label_color, label_size)

    if unseen.any():
        veil = np.zeros((h, w, 4))
        veil[unseen, 3] = VEIL_ALPHA
        ax.imshow(veil, interpolation="nearest", origin="upper", zorder=3.5)
        for r, c in np.argwhere(grid == "?"):
            ax.text(c, r, "?", ha="center", va="center", color="white", fontweight="bold",
                    fontsize=label_size * 1.5, zorder=4.5)

    for i, ((r, c), d) in enumerate(zip(state.agent_pos, state.agent_dir)):
        if env.roles[i] == ENGINEER:
            ax.add_patch(Circle((c, r), 0.47, color=agent_colour(i), zorder=3.6))
        else:
            ax.add_patch(Rectangle((c - 0.5, r - 0.5), 1, 1, color=agent_colour(i), zorder=3.6))
        dr, dc = DIR_DELTA[d]
        tip = np.array([c + 0.38 * dc, r + 0.38 * dr])
        base = np.array([c - 0.22 * dc, r - 0.22 * dr])
        side = 0.3 * np.array([-dr, dc])  # perpendicular to the facing direction, in (x, y)
        ax.add_patch(Polygon([tip, base + side, base - side], closed=True, color="white", zorder=4))
        _corner_label(ax, r, c, i, "white", label_size)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    if title is not None:
        ax.set_title(title, fontsize=9 * scale)
    if legend:
        _legend(ax, _legend_entries(env, fog=fog, candidates=candidates, fontsize=8 * scale), ax.figure.get_figwidth(),
                8 * scale)
    return ax


def _font_scale(width: float) -> float:
    """Text grows with a wide picture (a big map), so that it stays legible when shown at a page's width."""
    return max(1.0, width / 8)


def _corner_label(ax, r, c, index: int, color: str, size: float) -> None:
    from matplotlib import patheffects

    outline = patheffects.withStroke(linewidth=1.5, foreground="#202020" if color == "white" else "white")
    ax.text(c - 0.44, r - 0.44, str(index), color=color, fontsize=size, fontweight="bold", ha="left", va="top",
            zorder=5, path_effects=[outline])


def _legend_entries(env: USAREnv, trail: bool = False, fog: bool = False, candidates: bool = False,
                    fontsize: float = 8) -> dict:
    """The key to the colours, only what ``env``'s map uses: label -> a legend handle (a tuple draws a
    mark over a square), sized for text of ``fontsize`` points."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    grow = fontsize / 8

    def cell(color, mark=None, mark_color="white", size=5, shape="s"):
        square = Line2D([], [], marker=shape, markersize=11 * grow, color=color, linestyle="")
        return square if mark is None else (square, Line2D([], [], marker=mark, markersize=size * grow,
                                                           color=mark_color, linestyle=""))

    entries = {}
    for i, role in enumerate(env.roles):
        entries[f"{ROLE_WORDS[int(role)]} {i}"] = cell(agent_colour(i), ">", shape="o" if role == ENGINEER else "s")
    kinds = set(env.victim_kind.tolist())
    if 0 in kinds:
        entries["victim" if kinds == {0} else "regular victim"] = cell(VICTIM)
    if CRITICAL in kinds:
        entries["critical victim"] = cell(CRITICAL_VICTIM, "$!$", size=7)
    if 0 in kinds:
        entries["triaged"] = cell(TRIAGED_VICTIM, r"$\checkmark$", CHECK, 7)
    if CRITICAL in kinds:
        entries["triaged critical"] = cell(TRIAGED_CRITICAL, r"$\checkmark$", CRITICAL_CHECK, 7)
    if env.expires:
        entries["dead"] = cell(DEAD_VICTIM, "x", size=6)
    if env.has_rubble:
        entries["rubble"] = Patch(facecolor=RUBBLE, edgecolor=RUBBLE_LINES, hatch="////", linewidth=0)
        entries["rubble cleared"] = cell(FLOOR, ".", RUBBLE, 8)
    entries["wall"] = cell(WALL)
    if env.layout.obstacle.any():
        entries["obstacle"] = cell(OBSTACLE)
    if candidates and len(env.layout.random_cells):
        entries["a victim may be drawn here"] = cell(FLOOR, "$?$", "#6a6a6a", 7)
    if fog:
        veiled = "#575757"  # the floor under the veil
        entries["not seen by the team"] = cell(veiled)
        entries["not seen: may hold a victim"] = cell(veiled, "$?$", "white", 7)
    if trail:
        entries["path so far"] = Line2D([], [], color="#808080", alpha=0.6, linewidth=2.5 * grow)
    return entries


def _entry_width(label: str, fontsize: float) -> float:
    """Inches one legend entry takes in a row (handle, gap, text, column spacing), roughly."""
    return (1.0 + 0.8 + 1.4 + 0.58 * len(label)) * fontsize / 72


def _legend_columns(entries: dict, width: float, fontsize: float) -> int:
    """The most columns whose rows (read across) fit ``width`` inches."""
    labels = list(entries)
    for ncol in range(len(labels), 1, -1):
        widest = [max(_entry_width(s, fontsize) for s in labels[j::ncol]) for j in range(ncol)]
        if sum(widest) <= 0.96 * width:
            return ncol
    return 1


def _legend_rows(entries: dict, width: float, fontsize: float) -> int:
    return -(-len(entries) // _legend_columns(entries, width, fontsize))


def _legend(owner, entries: dict, width: float, fontsize: float, **placement) -> None:
    """The key in as few rows as fit ``width`` inches, read across the rows, on an Axes (below the map)
    or a Figure (``placement``: where)."""
    from matplotlib.legend_handler import HandlerTuple

    ncol = _legend_columns(entries, width, fontsize)
    n, rows = len(entries), -(-len(entries) // ncol)
    # matplotlib fills columns first, the first n % ncol of them one longer: order the entries so rows read across
    sizes = [rows if (n % ncol == 0 or j < n % ncol) else rows - 1 for j in range(ncol)]
    order = [i * ncol + j for j in range(ncol) for i in range(sizes[j])]
    labels = [list(entries)[k] for k in order]
    placement = placement or {"loc": "upper center", "bbox_to_anchor": (0.5, -0.02)}
    owner.legend([entries[s] for s in labels], labels, handler_map={tuple: HandlerTuple(ndivide=1)},
                 ncol=ncol, frameon=False, handlelength=1.0, columnspacing=1.4, fontsize=fontsize, **placement)


def _unstack(env: USAREnv, states) -> list[EnvState]:
    """A list of unbatched states from a list of them or one EnvState with a leading time axis."""
    if isinstance(states, EnvState):
        states = jax.tree.map(np.asarray, states)
        if states.agent_pos.ndim != 3:
            raise ValueError(f"an EnvState episode needs a leading time axis (agent_pos [T, n_agents, 2]), "
                             f"got agent_pos of shape {states.agent_pos.shape}")
        states = [jax.tree.map(lambda x, k=k: x[k], states) for k in range(states.agent_pos.shape[0])]
    return [_numpy_state(env, s) for s in states]


def frame_indices(n: int, max_frames: int) -> np.ndarray:
    """At most ``max_frames`` indices of ``range(n)``, evenly spread, always the first and the last."""
    if max_frames < 2 and n > 1:
        raise ValueError(f"max_frames must be at least 2 to keep the first and last frames, got {max_frames}")
    return np.unique(np.floor(np.linspace(0, n - 1, min(n, max_frames)) + 0.5).astype(int))


STRIP_CELLS = 64  # a strip's frames side by side span about this many grid cells (fewer columns on wide maps)
STRIP_FONT = 20  # points, for a strip about 19 inches (64 cells) wide: ~10 px when shown 900 px wide


def save_episode_strip(env: USAREnv, states, path, titles=None, max_frames: int = 12, cols: int | None = None,
                       rewards=None, suptitle: str | None = None, fog: bool | None = None) -> Path:
    """Save an episode as a grid of frames (PNG) and return the path.

    ``states``: a list of EnvStates or one EnvState with a leading time axis. At most ``max_frames``
    frames, evenly sub-sampled, first and last always kept, ``cols`` per row (default: as many as make
    about ``STRIP_CELLS`` grid cells across, 2 to 6, so the frames stay legible at a page's width). Each
    frame is titled ``t=..`` (or ``titles[k]`` for state k), plus the return so far when ``rewards`` is
    given (float[len(states) - 1], the reward of each step). Each agent's path up to the frame is drawn
    faintly in its colour. ``suptitle``: a line above the whole strip. ``fog``: as in ``render_state``.
    """
    states = _unstack(env, states)
    if not states:
        raise ValueError("save_episode_strip needs at least one state")
    if titles is not None and len(titles) != len(states):
        raise ValueError(f"titles has {len(titles)} entries for {len(states)} states")
    returns = None
    if rewards is not None:
        rewards = np.asarray(rewards, float).reshape(-1)
        if len(rewards) != len(states) - 1:
            raise ValueError(f"rewards has {len(rewards)} entries; expected one per step ({len(states) - 1})")
        returns = np.concatenate([[0.0], np.cumsum(rewards)])
    h, w = env.layout.shape
    if cols is None:
        cols = int(np.clip(round(STRIP_CELLS / w), 2, 6))
    if cols < 1:
        raise ValueError(f"cols must be at least 1, got {cols}")
    keep = frame_indices(len(states), max_frames)
    cols = min(cols, len(keep))
    rows = -(-len(keep) // cols)
    fog = _fog(env, fog)
    cell = 0.3  # inches per grid cell; the agent and victim numbers take ~40% of a cell
    width = max(cols * (w * cell + 0.15), 6.0)
    fontsize = float(np.clip(STRIP_FONT * width / (STRIP_CELLS * cell), 9, STRIP_FONT))  # smaller on a small strip
    lines = [] if suptitle is None else [line for part in suptitle.split("\n")
                                         for line in textwrap.wrap(part, max(20, int(width * 72 / (0.6 * fontsize))))]
    frame_titles = []
    for k in keep:
        title = titles[k] if titles is not None else f"t={int(states[k].t)}"
        frame_titles.append(title + (f"  R={returns[k]:g}" if returns is not None else ""))
    # as large as the strip's text while the longest frame title fits its frame
    title_size = max(6.0, min(fontsize, w * cell * 72 / (0.62 * max(map(len, frame_titles)))))
    entries = _legend_entries(env, trail=True, fog=fog, fontsize=fontsize)
    fig, axes = _figure(width, rows * (h * cell + 0.2 + title_size / 50) + (fontsize / 50) * len(lines)
                        + (fontsize / 50) * _legend_rows(entries, width, fontsize) + 0.3, rows, cols)
    positions = np.stack([s.agent_pos for s in states])
    for ax, k, title in zip(axes.flat, keep, frame_titles):
        render_state(env, states[k], ax=ax, title=title, trail=positions[:k], label_size=cell * 72 * 0.4, fog=fog)
        ax.title.set_fontsize(title_size)
    for ax in axes.flat[len(keep):]:
        ax.set_axis_off()
    if lines:
        fig.suptitle("\n".join(lines), fontsize=fontsize)
    _legend(fig, entries, width, fontsize, loc="outside lower center")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path


@lru_cache(maxsize=32)
def _jit_step(env: USAREnv):
    return jax.jit(env.step)


def reset_state(env: USAREnv, key: jax.Array | None = None) -> EnvState:
    """The reset state ``rollout_states(env, ..., key)`` starts from (victims drawn with a key split off
    ``key``; default ``jax.random.key(0)``)."""
    key = jax.random.key(0) if key is None else key
    # env.reset's state without its observation (the "view" one costs seconds outside jit)
    return env.initial_state(jax.random.split(key)[1] if env.n_drawn else None)


def rollout_states(env: USAREnv, actions, key: jax.Array | None = None) -> tuple[list[EnvState], np.ndarray]:
    """Play ``actions`` int[T, n_agents] from the reset state, stopping at the first ``done``.

    Returns (states, rewards): the reset state (``reset_state(env, key)``) and every state after it (len =
    steps + 1), and float32[steps] the team reward of each step. Actions are checked like ``env.step``
    checks them.
    """
    actions = np.asarray(actions)
    if actions.ndim != 2:
        raise ValueError(f"actions must be int[T, {env.n_agents}] (one row per step), got shape {actions.shape}")
    for row in actions:
        env._check_actions(row)
    key = jax.random.key(0) if key is None else key
    state = reset_state(env, key)
    step = _jit_step(env)
    states, rewards = [state], []
    for row in actions:
        key, step_key = jax.random.split(key)
        _, state, reward, done, _ = step(step_key, state, row.astype(np.int32))
        states.append(state)
        rewards.append(float(reward))
        if done:
            break
    return states, np.asarray(rewards, np.float32)


def save_map(env: USAREnv, path, title: str | None = None, state: EnvState | None = None) -> Path:
    """A map picture: every region tinted and named (the graph view over the map) under ``state`` (default:
    the reset state; victims drawn at reset are drawn with ``reset_state(env)``'s key), the '?' cells where
    victims may be drawn marked, nothing veiled; returns ``path``."""
    from matplotlib.colors import to_rgba

    state = reset_state(env) if state is None else state
    if title is None:
        drawn = " (one draw of its victims)" if env.n_drawn else ""
        title = f"{env.layout.name}: reset state{drawn} and regions"
    ax = render_state(env, state, title=title, legend=True, fog=False, candidates=True)
    scale = _font_scale(ax.figure.get_figwidth())
    region = env.graph.cell_region
    tint = np.zeros(region.shape + (4,))
    taken = np.zeros(region.shape, bool)  # labels go where no agent or victim stands
    taken[tuple(np.asarray(state.agent_pos).T)] = True
    taken[tuple(np.asarray(state.victim_pos if state.victim_pos is not None else env.victim_pos).T)] = True
    rooms, hall_tint = 0, {}
    for r, (name, kind) in enumerate(zip(env.graph.names, env.graph.kinds)):
        cells = region == r
        if kind == "hall":  # greedily a tint no touching hall piece has, so the cuts between pieces show
            used = {hall_tint.get(q) for q in np.flatnonzero(env.graph.adjacency[r])}
            hall_tint[r] = next((t for t in HALL_TINTS if t not in used), HALL_TINTS[0])
            color = hall_tint[r]
        else:
            color, rooms = ROOM_TINTS[rooms % len(ROOM_TINTS)], rooms + 1
        tint[cells] = to_rgba(color, 0.6)
        rows, cols = np.nonzero(cells & ~taken) if (cells & ~taken).any() else np.nonzero(cells)
        k = np.argmin((rows - rows.mean()) ** 2 + (cols - cols.mean()) ** 2)  # a free cell near the middle
        ax.text(cols[k], rows[k], name, ha="center", va="center", fontsize=6 * min(scale, 1.5), zorder=5,
                bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.75))
    ax.imshow(tint, interpolation="nearest", origin="upper", zorder=1)
    path = Path(path)
    ax.figure.savefig(path, dpi=120, bbox_inches="tight")
    return path
