"""Pictures of USAR states: ASCII for terminals and tests, matplotlib in the paper's Fig. 2 colours.

Side effects (files, figures) live here and in the CLI only; nothing here is called inside ``jit``.
Every function takes one unbatched ``EnvState`` (or a list of them); jax arrays are read with numpy.
"""

from __future__ import annotations

import textwrap
from functools import lru_cache
from pathlib import Path

import jax
import numpy as np

from jaxusar.envs.usar import DIR_DELTA, EnvState, USAREnv

ARROWS = ">v<^"  # EAST SOUTH WEST NORTH, indexed by direction
# The paper's Fig. 2 palette.
FLOOR, WALL, OBSTACLE = "#c0c0c0", "#000000", "#2d2d2d"
VICTIM, TRIAGED_VICTIM, MEDIC = "#3f9b35", "#a6d99c", "#2626ff"
CHECK = "#1d5c17"  # the check mark on a triaged victim
GRID = "#d9d9d9"
# region tints of a map picture: warm and violet pastels, none near the victims' green or the medics' blue
ROOM_TINTS = ("#f4a582", "#d6a5c9", "#f7d08a", "#c7b8e8", "#f2b6b6", "#e8c39e", "#e7a1b0", "#d9c27e")
HALL_TINT = "#fff7c2"


def _numpy_state(state: EnvState) -> EnvState:
    state = jax.tree.map(np.asarray, state)
    if state.agent_pos.ndim != 2:
        raise ValueError(f"expected one unbatched EnvState (agent_pos [n_agents, 2]), got agent_pos "
                         f"of shape {state.agent_pos.shape}; index the batch first")
    return state


def render_ascii(env: USAREnv, state: EnvState) -> str:
    """The map as text: ``#`` wall, ``X`` obstacle, ``.`` floor, ``V`` untriaged / ``+`` triaged victim,
    each agent an arrow of its facing direction (``> v < ^``); last line ``t=3 triaged=[0 1]``."""
    state = _numpy_state(state)
    grid = np.array([list(row) for row in env.layout.to_ascii().splitlines()])
    grid[grid == "A"] = "."
    for (r, c), done in zip(env.victim_pos, state.triaged):
        grid[r, c] = "+" if done else "V"
    for (r, c), d in zip(state.agent_pos, state.agent_dir):
        grid[r, c] = ARROWS[d]
    rows = ["".join(row) for row in grid]
    return "\n".join(rows + [f"t={int(state.t)} triaged={state.triaged.astype(int)}"])


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
                 legend: bool = False, label_size: float = 6):
    """Draw one state in the colours of the paper's Fig. 2 and return the matplotlib Axes.

    Floor light grey, walls black, obstacles dark grey, victims green (triaged: pale green with a dark
    check mark), medics blue with a white arrow for the facing direction. Medics and victims carry their
    index in the top-left corner (``label_size`` points). ``trail``: optional int[T, n_agents, 2] of
    earlier positions, drawn as a faint path per medic. ``legend``: a key to the colours below the map.
    """
    from matplotlib.patches import Polygon, Rectangle

    state = _numpy_state(state)
    h, w = env.layout.shape
    if ax is None:  # with a legend, wide enough for its one row even on a small map
        ax = _figure(max(0.45 * w + 0.4, 7.5 if legend else 0), 0.45 * h + (1.0 if legend else 0.6))[1][0, 0]
    ax.imshow(_map_image(env), interpolation="nearest", origin="upper")
    ax.set_xticks(np.arange(-0.5, w, 1), minor=True)
    ax.set_yticks(np.arange(-0.5, h, 1), minor=True)
    ax.grid(which="minor", color=GRID, linewidth=0.6)
    ax.tick_params(which="both", length=0, labelbottom=False, labelleft=False)
    for spine in ax.spines.values():
        spine.set_color("#808080")

    if trail is not None:
        trail = np.asarray(trail).reshape(-1, env.n_agents, 2)
        for i in range(env.n_agents):
            path = np.concatenate([trail[:, i], state.agent_pos[None, i]])
            ax.plot(path[:, 1], path[:, 0], color=MEDIC, alpha=0.35, linewidth=2.5, zorder=2,
                    solid_capstyle="round", solid_joinstyle="round")

    for v, ((r, c), done) in enumerate(zip(env.victim_pos, state.triaged)):
        ax.add_patch(Rectangle((c - 0.5, r - 0.5), 1, 1, color=TRIAGED_VICTIM if done else VICTIM, zorder=3))
        if done:  # a check mark as well as the paler green, so triage reads without colour vision
            ax.plot([c - 0.28, c - 0.06, c + 0.3], [r + 0.02, r + 0.25, r - 0.25], color=CHECK,
                    linewidth=2.5, solid_capstyle="round", zorder=4)
        _corner_label(ax, r, c, v, CHECK if done else "white", label_size)

    for i, ((r, c), d) in enumerate(zip(state.agent_pos, state.agent_dir)):
        ax.add_patch(Rectangle((c - 0.5, r - 0.5), 1, 1, color=MEDIC, zorder=3))
        dr, dc = DIR_DELTA[d]
        tip = np.array([c + 0.38 * dc, r + 0.38 * dr])
        base = np.array([c - 0.22 * dc, r - 0.22 * dr])
        side = 0.3 * np.array([-dr, dc])  # perpendicular to the facing direction, in (x, y)
        ax.add_patch(Polygon([tip, base + side, base - side], closed=True, color="white", zorder=4))
        _corner_label(ax, r, c, i, "white", label_size)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    if title is not None:
        ax.set_title(title, fontsize=9)
    if legend:
        _legend(ax)
    return ax


def _corner_label(ax, r, c, index: int, color: str, size: float) -> None:
    from matplotlib import patheffects

    outline = patheffects.withStroke(linewidth=1.5, foreground="#202020" if color == "white" else "white")
    ax.text(c - 0.44, r - 0.44, str(index), color=color, fontsize=size, fontweight="bold", ha="left", va="top",
            zorder=5, path_effects=[outline])


def _legend_entries(trail: bool = False) -> dict:
    """The key to the colours: label -> a legend handle (a tuple draws a mark over a square)."""
    from matplotlib.lines import Line2D

    def cell(color, mark=None, mark_color="white", size=5):
        square = Line2D([], [], marker="s", markersize=11, color=color, linestyle="")
        return square if mark is None else (square, Line2D([], [], marker=mark, markersize=size,
                                                           color=mark_color, linestyle=""))

    entries = {"medic N (facing east)": cell(MEDIC, ">"), "victim N": cell(VICTIM),
               "triaged victim": cell(TRIAGED_VICTIM, r"$\checkmark$", CHECK, 7),
               "wall": cell(WALL), "obstacle": cell(OBSTACLE)}
    if trail:
        entries["a medic's path so far"] = Line2D([], [], color=MEDIC, alpha=0.35, linewidth=2.5)
    return entries


def _legend(owner, trail: bool = False, **placement) -> None:
    """The colour key in one row, on an Axes (below the map) or a Figure (``placement``: where)."""
    from matplotlib.legend_handler import HandlerTuple

    entries = _legend_entries(trail)
    placement = placement or {"loc": "upper center", "bbox_to_anchor": (0.5, -0.02), "fontsize": 8}
    owner.legend(list(entries.values()), list(entries), handler_map={tuple: HandlerTuple(ndivide=1)},
                 ncol=len(entries), frameon=False, handlelength=1.0, columnspacing=1.4, **placement)


def _unstack(states) -> list[EnvState]:
    """A list of unbatched states from a list of them or one EnvState with a leading time axis."""
    if isinstance(states, EnvState):
        states = jax.tree.map(np.asarray, states)
        if states.agent_pos.ndim != 3:
            raise ValueError(f"an EnvState episode needs a leading time axis (agent_pos [T, n_agents, 2]), "
                             f"got agent_pos of shape {states.agent_pos.shape}")
        return [jax.tree.map(lambda x, k=k: x[k], states) for k in range(states.agent_pos.shape[0])]
    return [_numpy_state(s) for s in states]


def frame_indices(n: int, max_frames: int) -> np.ndarray:
    """At most ``max_frames`` indices of ``range(n)``, evenly spread, always the first and the last."""
    if max_frames < 2 and n > 1:
        raise ValueError(f"max_frames must be at least 2 to keep the first and last frames, got {max_frames}")
    return np.unique(np.floor(np.linspace(0, n - 1, min(n, max_frames)) + 0.5).astype(int))


def save_episode_strip(env: USAREnv, states, path, titles=None, max_frames: int = 12, cols: int = 6,
                       rewards=None, suptitle: str | None = None) -> Path:
    """Save an episode as a grid of frames (PNG) and return the path.

    ``states``: a list of EnvStates or one EnvState with a leading time axis. At most ``max_frames``
    frames, evenly sub-sampled, first and last always kept. Each frame is titled ``t=..`` (or
    ``titles[k]`` for state k), plus the return so far when ``rewards`` is given (float[len(states) - 1],
    the reward of each step). Each medic's path up to the frame is drawn faintly. ``suptitle``: a line
    above the whole strip.
    """
    states = _unstack(states)
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
    if cols < 1:
        raise ValueError(f"cols must be at least 1, got {cols}")
    keep = frame_indices(len(states), max_frames)
    cols = min(cols, len(keep))
    rows = -(-len(keep) // cols)
    h, w = env.layout.shape
    cell = 0.3  # inches per grid cell; the medic and victim numbers take ~40% of a cell
    width = cols * (w * cell + 0.15)
    lines = [] if suptitle is None else [line for part in suptitle.split("\n")
                                         for line in textwrap.wrap(part, max(20, int(width * 72 / 6.6)))]
    fig, axes = _figure(width, rows * (h * cell + 0.45) + 0.2 * len(lines) + 0.5, rows, cols)
    positions = np.stack([s.agent_pos for s in states])
    for ax, k in zip(axes.flat, keep):
        title = titles[k] if titles is not None else f"t={int(states[k].t)}"
        if returns is not None:
            title += f"  R={returns[k]:g}"
        render_state(env, states[k], ax=ax, title=title, trail=positions[:k], label_size=cell * 72 * 0.4)
    for ax in axes.flat[len(keep):]:
        ax.set_axis_off()
    if lines:
        fig.suptitle("\n".join(lines), fontsize=11)
    _legend(fig, trail=True, loc="outside lower center", fontsize=9)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path


@lru_cache(maxsize=32)
def _jit_step(env: USAREnv):
    return jax.jit(env.step)


def rollout_states(env: USAREnv, actions, key: jax.Array | None = None) -> tuple[list[EnvState], np.ndarray]:
    """Play ``actions`` int[T, n_agents] from the reset state, stopping at the first ``done``.

    Returns (states, rewards): the reset state and every state after it (len = steps + 1), and
    float32[steps] the team reward of each step. Actions are checked like ``env.step`` checks them.
    """
    actions = np.asarray(actions)
    if actions.ndim != 2:
        raise ValueError(f"actions must be int[T, {env.n_agents}] (one row per step), got shape {actions.shape}")
    for row in actions:
        env._check_actions(row)
    key = jax.random.key(0) if key is None else key
    key, reset_key = jax.random.split(key)
    step = _jit_step(env)
    _, state = env.reset(reset_key)
    states, rewards = [state], []
    for row in actions:
        key, step_key = jax.random.split(key)
        _, state, reward, done, _ = step(step_key, state, row.astype(np.int32))
        states.append(state)
        rewards.append(float(reward))
        if done:
            break
    return states, np.asarray(rewards, np.float32)


def save_map(env: USAREnv, path, title: str | None = None) -> Path:
    """The reset state with every region tinted and named (the graph view over the map); returns ``path``."""
    from matplotlib.colors import to_rgba

    _, state = env.reset(None)
    ax = render_state(env, state, title=title or f"{env.layout.name}: reset state and regions", legend=True)
    region = env.graph.cell_region
    tint = np.zeros(region.shape + (4,))
    rooms = 0
    for r, (name, kind) in enumerate(zip(env.graph.names, env.graph.kinds)):
        cells = region == r
        color = HALL_TINT if kind == "hall" else ROOM_TINTS[rooms % len(ROOM_TINTS)]
        rooms += kind != "hall"
        tint[cells] = to_rgba(color, 0.6)
        rows, cols = np.nonzero(cells)
        k = np.argmin((rows - rows.mean()) ** 2 + (cols - cols.mean()) ** 2)  # a cell of the region near its middle
        ax.text(cols[k], rows[k], name, ha="center", va="center", fontsize=6, zorder=5,
                bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.75))
    ax.imshow(tint, interpolation="nearest", origin="upper", zorder=1)
    path = Path(path)
    ax.figure.savefig(path, dpi=120, bbox_inches="tight")
    return path
