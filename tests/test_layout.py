"""Layouts, region grids and the graph view: the shipped map against the paper, and every bad input."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxusar import envs
from jaxusar.envs import LayoutError, parse_layout

# The 10 map rows of PAPER.md (read off the paper's Fig. 2), copied here verbatim.
PAPER_MAP = """\
V...#.........A
....#..........
....#..........
...............
###............
.......XX...###
.......XX......
...............
...........#.V.
A..........#..."""

ONE_REGION = "R all hall\n---\n"


def regions_for(grid: str, letter: str = "R") -> str:
    """A one-region grid matching ``grid``: '#' on walls and obstacles, ``letter`` elsewhere."""
    rows = ["".join("#" if ch in "#X" else letter for ch in row) for row in grid.splitlines()]
    return f"{letter} all hall\n---\n" + "\n".join(rows)


def parse(grid: str, name: str = "tiny") -> envs.Layout:
    return parse_layout(grid, regions_for(grid), name)


# -- the shipped two-rooms map -----------------------------------------------------------------
def test_two_rooms_equals_the_paper_map():
    layout = envs.load_layout("two_rooms")
    assert layout.to_ascii() == PAPER_MAP
    assert layout.shape == (10, 15)
    # PAPER.md: agent 0 = top medic (0,14), agent 1 = bottom medic (9,0);
    # victim 0 = top (0,0), victim 1 = bottom (8,13).
    np.testing.assert_array_equal(layout.agent_start, [[0, 14], [9, 0]])
    np.testing.assert_array_equal(layout.victim_pos, [[0, 0], [8, 13]])
    # The dark 2x2 block is an obstacle, not a wall; both are blocked.
    np.testing.assert_array_equal(np.argwhere(layout.obstacle), [[5, 7], [5, 8], [6, 7], [6, 8]])
    assert layout.wall.sum() == PAPER_MAP.count("#") == 11
    assert not (layout.wall & layout.obstacle).any()
    np.testing.assert_array_equal(layout.blocked, layout.wall | layout.obstacle)


def test_two_rooms_env_exposes_the_map():
    env = envs.make("two_rooms")
    assert (env.n_agents, env.n_victims, env.horizon) == (2, 2, 100)
    assert (env.triage_reward, env.step_penalty, env.start_dir) == (100.0, 0.0, envs.NORTH)
    assert env.blocked.dtype == bool and env.blocked.shape == (10, 15)
    chars = np.array([list(r) for r in PAPER_MAP.splitlines()])
    np.testing.assert_array_equal(env.blocked, (chars == "#") | (chars == "X"))
    assert env.victim_pos.dtype == np.int32
    np.testing.assert_array_equal(env.victim_pos, [[0, 0], [8, 13]])
    assert env.obs_dim == 2 * (10 + 15 + 4) + 2 == 60
    assert "two_rooms" in envs.available_layouts()


def test_two_rooms_regions_match_the_paper():
    layout = envs.load_layout("two_rooms")
    assert layout.region_names == ("top_room", "hall_way", "bottom_room")
    assert layout.region_kinds == ("room", "hall", "room")
    top, hall, bottom = 0, 1, 2
    open_ = ~layout.blocked
    rows, cols = np.indices(layout.shape)
    # PAPER.md: top room = rows 0-3, cols 0-3; bottom room = rows 6-9, cols 12-14; hall-way = the rest.
    in_top = (rows <= 3) & (cols <= 3)
    in_bottom = (rows >= 6) & (cols >= 12)
    np.testing.assert_array_equal(layout.region == top, in_top & open_)
    np.testing.assert_array_equal(layout.region == bottom, in_bottom & open_)
    np.testing.assert_array_equal(layout.region == hall, ~in_top & ~in_bottom & open_)
    np.testing.assert_array_equal(layout.region == -1, layout.blocked)
    assert in_top.sum() == 16 and (in_bottom & open_).sum() == 12


# -- the graph view ----------------------------------------------------------------------------
def test_region_graph_of_two_rooms():
    g = envs.make("two_rooms").graph
    assert g.n_regions == 3
    assert g.index("top_room") == 0 and g.index("hall_way") == 1 and g.index("bottom_room") == 2
    assert g.edges() == [("top_room", "hall_way"), ("hall_way", "bottom_room")]
    np.testing.assert_array_equal(g.adjacency, [[0, 1, 0], [1, 0, 1], [0, 1, 0]])
    assert not g.adjacency[0, 2] and not g.adjacency[2, 0]  # no top-bottom edge
    np.testing.assert_array_equal(g.victim_region, [0, 2])
    assert g.rooms == (0, 2)
    with pytest.raises(KeyError, match="no region 'kitchen'"):
        g.index("kitchen")


def test_adjacency_needs_two_open_cells_sharing_an_edge():
    # L and R are separated by a wall cell: not adjacent; M touches both.
    g = envs.RegionGraph(parse_layout("A#V\n...", "L left room\nR right room\nM mid hall\n---\nL#R\nMMM", "wall"))
    assert g.edges() == [("left", "mid"), ("right", "mid")]
    # L and R touch only diagonally: not adjacent.
    g = envs.RegionGraph(parse_layout("A.\n.V", "L left room\nR right room\nM mid hall\n---\nLM\nMR", "diag"))
    assert g.edges() == [("left", "mid"), ("right", "mid")]
    assert not g.adjacency.diagonal().any()
    np.testing.assert_array_equal(g.adjacency, g.adjacency.T)


def test_abstract_state_and_region_of():
    env = envs.make("two_rooms")
    g = env.graph
    _, state = env.reset(None)
    regions, triaged = g.abstract_state(state)
    np.testing.assert_array_equal(regions, [1, 1])  # both medics start in the hall-way
    np.testing.assert_array_equal(triaged, [False, False])
    moved = state.replace(agent_pos=jnp.array([[3, 3], [7, 12]], jnp.int32), triaged=jnp.array([True, False]))
    regions, triaged = jax.jit(g.abstract_state)(moved)
    np.testing.assert_array_equal(regions, [0, 2])
    np.testing.assert_array_equal(triaged, [True, False])
    # (3,4) and (6,11) are the hall-way cells at the two doors.
    np.testing.assert_array_equal(g.region_of(jnp.array([[3, 4], [6, 11], [9, 14], [4, 0]])), [1, 1, 2, -1])
    batch = jax.tree.map(lambda a, b: jnp.stack([a, b]), state, moved)
    regions, triaged = jax.vmap(g.abstract_state)(batch)
    np.testing.assert_array_equal(regions, [[1, 1], [0, 2]])
    assert regions.dtype == jnp.int32


def test_subset_keeps_map_and_chosen_agents_and_victims():
    layout = envs.load_layout("two_rooms")
    sub = layout.subset(agents=[1], victims=[0])
    np.testing.assert_array_equal(sub.agent_start, [[9, 0]])
    np.testing.assert_array_equal(sub.victim_pos, [[0, 0]])
    np.testing.assert_array_equal(sub.wall, layout.wall)
    np.testing.assert_array_equal(sub.obstacle, layout.obstacle)
    np.testing.assert_array_equal(sub.region, layout.region)
    assert sub.region_names == layout.region_names and sub.name == layout.name
    # order given is kept, the original is untouched, None keeps all
    np.testing.assert_array_equal(layout.subset(agents=[1, 0]).agent_start, [[9, 0], [0, 14]])
    np.testing.assert_array_equal(layout.agent_start, [[0, 14], [9, 0]])
    np.testing.assert_array_equal(layout.subset(victims=[1]).agent_start, layout.agent_start)
    assert layout.subset(victims=[]).victim_pos.shape == (0, 2)
    # the removed victim's cell becomes walkable floor in an env built from the subset
    env = envs.make(layout.subset(agents=[0], victims=[1]))
    assert (env.n_agents, env.n_victims) == (1, 1)
    assert env.layout.to_ascii().count("V") == 1 and env.layout.to_ascii()[0] == "."  # (0,0) is floor now
    np.testing.assert_array_equal(env.graph.victim_region, [2])


# -- parsing -----------------------------------------------------------------------------------
def test_parse_with_and_without_header():
    grid = "A.#\n.XV\n..."
    plain = parse_layout(grid, regions_for(grid))
    headed = parse_layout("; a comment\n; another\n---\n" + grid + "\n\n",
                          "; legend\n" + regions_for(grid), "headed")
    for layout in (plain, headed):
        assert layout.to_ascii() == grid
        np.testing.assert_array_equal(layout.agent_start, [[0, 0]])
        np.testing.assert_array_equal(layout.victim_pos, [[1, 2]])
        np.testing.assert_array_equal(layout.wall, [[0, 0, 1], [0, 0, 0], [0, 0, 0]])
        np.testing.assert_array_equal(layout.obstacle, [[0, 0, 0], [0, 1, 0], [0, 0, 0]])
        np.testing.assert_array_equal(layout.region, [[0, 0, -1], [0, -1, 0], [0, 0, 0]])
    assert plain.name == "<string>" and headed.name == "headed"


def test_agents_and_victims_are_numbered_row_major():
    grid = "..VA\nA...\nV..A"
    layout = parse(grid)
    np.testing.assert_array_equal(layout.agent_start, [[0, 3], [1, 0], [2, 3]])
    np.testing.assert_array_equal(layout.victim_pos, [[0, 2], [2, 0]])


def test_load_layout_from_a_path(tmp_path):
    grid = "A.V"
    (tmp_path / "mine.txt").write_text(grid)
    (tmp_path / "mine.regions.txt").write_text(regions_for(grid))
    layout = envs.load_layout(str(tmp_path / "mine.txt"))
    assert layout.name == "mine" and layout.to_ascii() == grid
    assert envs.make(str(tmp_path / "mine.txt")).n_agents == 1


# -- bad inputs: each error names its problem ----------------------------------------------------
def test_unknown_map_name():
    with pytest.raises(LayoutError, match="unknown map 'atlantis'.*two_rooms"):
        envs.make("atlantis")
    with pytest.raises(LayoutError, match="unknown map"):
        envs.load_layout("/no/such/file.txt")
    assert issubclass(LayoutError, ValueError)


@pytest.mark.parametrize("grid, message", [
    ("A.V\n..", "ragged grid: row 0 has 3 columns but row 1 has 2"),
    ("A.V\n...\n....", "ragged grid: row 0 has 3 columns but row 2 has 4"),
    ("A.V\n\n...", "ragged grid"),  # a blank line inside the grid
    ("", "no grid rows found"),
    ("\n\n  \n", "no grid rows found"),
    ("a header\n---\n", "no grid rows found"),
    ("A.Z\n..V", "unknown character 'Z' at row 0, col 2"),
    ("A.V\n.o.", "unknown character 'o' at row 1, col 1"),
    ("A.V \n... ", "unknown character ' '"),
    ("...\n..V", "no agent start ('A' medic or 'E' engineer)"),
    ("A..\n...", "no victim ('V' regular, 'C' critical"),
    ("A.#V", "victim 0 at (0, 3) cannot be reached by any medic, even with every rubble cleared"),
    ("A.V\nXX.\n.VX\n.X.", "victim 1 at (2, 1) cannot be reached"),
    ("AX.\nX..\n..V", "victim 0 at (2, 2) cannot be reached"),
])
def test_bad_layout(grid, message):
    with pytest.raises(LayoutError, match=re.escape(message)) as info:
        parse_layout(grid, regions_for(grid), "bad")
    assert "layout 'bad'" in str(info.value)


def test_victims_block_the_reachability_check():
    parse("AV")  # next to the start
    parse("A.V\n..V")
    # (0,3)'s only open neighbour holds the other victim, which no agent can stand on
    with pytest.raises(LayoutError, match=re.escape("victim 1 at (0, 3) cannot be reached")):
        parse("A.VV")


GRID = "A.#\n.XV\n..."


@pytest.mark.parametrize("regions, message", [
    ("R all hall\n---\nRR#\nR#", "ragged grid"),
    ("R all hall\n---\nRR#\nR#R\nRRR\nRRR", "grid is 4x3 but the layout is 3x3"),
    ("R all hall\n---\nRR#R\nR#RR", "grid is 2x4 but the layout is 3x3"),
    ("R all hall\n---\nRRR\nR#R\nRRR", "cell (0, 2) is 'R' but the layout needs '#' (wall or obstacle) there"),
    ("R all hall\n---\nRR#\nRRR\nRRR", "cell (1, 1) is 'R' but the layout needs '#'"),  # obstacle needs '#'
    ("R all hall\n---\n#R#\nR#R\nRRR", "cell (0, 0) is '#' but the layout needs a region letter (open cell)"),
    ("R all hall\n---\nRQ#\nR#R\nRRR", "letter 'Q' at (0, 1) is not in the legend ['R']"),
    ("R all hall\n---\nR.#\nR#R\nRRR", "letter '.' at (0, 1) is not in the legend"),
    ("RR#\nR#R\nRRR", "no legend lines"),
    ("; only a comment\n---\nRR#\nR#R\nRRR", "no legend lines"),
    ("R all\n---\nRR#\nR#R\nRRR", "legend line 'R all' is not 'letter name kind'"),
    ("RS all hall\n---\nRR#\nR#R\nRRR", "legend line 'RS all hall' is not 'letter name kind'"),
    ("R all hall extra\n---\nRR#\nR#R\nRRR", "is not 'letter name kind'"),
    ("R all corridor\n---\nRR#\nR#R\nRRR", "region 'all' has kind 'corridor'; expected one of ('room', 'hall')"),
    ("R a hall\nR b room\n---\nRR#\nR#R\nRRR", "legend letter 'R' is reserved or repeated"),
    ("# a hall\n---\nRR#\nR#R\nRRR", "legend letter '#' is reserved or repeated"),
    (". a hall\n---\nRR#\nR#R\nRRR", "legend letter '.' is reserved or repeated"),
    ("R all hall\n---\n", "no grid rows found"),
])
def test_bad_region_grid(regions, message):
    with pytest.raises(LayoutError, match=re.escape(message)) as info:
        parse_layout(GRID, regions, "rg")
    assert "region grid of 'rg'" in str(info.value)


def test_region_grid_may_use_several_letters():
    layout = parse_layout(GRID, "P a room\nQ b hall\n---\nPQ#\nQ#P\nPPP", "two")
    np.testing.assert_array_equal(layout.region, [[0, 1, -1], [1, -1, 0], [0, 0, 0]])
    assert layout.region_names == ("a", "b") and layout.region_kinds == ("room", "hall")


# -- bad overrides -------------------------------------------------------------------------------
@pytest.mark.parametrize("overrides, error, message", [
    ({"horizon": 1.5}, TypeError, "override horizon=1.5: expected int, got float"),
    ({"horizon": "100"}, TypeError, "override horizon='100': expected int, got str"),
    ({"horizon": True}, TypeError, "expected int, got bool"),
    ({"horizon": None}, TypeError, "expected int, got NoneType"),
    ({"horizon": 0}, ValueError, "override horizon=0 is out of range [1, 1000000]"),
    ({"horizon": -5}, ValueError, "override horizon=-5 is out of range"),
    ({"horizon": 10**7}, ValueError, "is out of range [1, 1000000]"),
    ({"triage_reward": "100"}, TypeError, "override triage_reward='100': expected float, got str"),
    ({"triage_reward": float("nan")}, ValueError, "override triage_reward=nan is out of range"),
    ({"step_penalty": float("-inf")}, ValueError, "override step_penalty=-inf is out of range"),
    ({"step_penalty": [1.0]}, TypeError, "expected float, got list"),
    ({"start_dir": 4}, ValueError, "override start_dir=4 is out of range [0, 3]"),
    ({"start_dir": -1}, ValueError, "override start_dir=-1 is out of range [0, 3]"),
    ({"start_dir": 1.0}, TypeError, "override start_dir=1.0: expected int, got float"),
    ({"start_dir": "UP"}, ValueError, "override start_dir='UP': expected one of ('EAST', 'SOUTH', 'WEST', 'NORTH')"),
    ({"gamma": 0.99}, TypeError, "unknown env override(s) ['gamma']; allowed: ['horizon'"),
])
def test_bad_override(overrides, error, message):
    with pytest.raises(error, match=re.escape(message)):
        envs.make("two_rooms", **overrides)


def test_good_overrides():
    env = envs.make("two_rooms", horizon=np.int64(300), triage_reward=5, step_penalty=-1.0, start_dir="south")
    assert (env.horizon, env.triage_reward, env.step_penalty, env.start_dir) == (300, 5.0, -1.0, envs.SOUTH)
    assert type(env.horizon) is int and type(env.triage_reward) is float
    _, state = env.reset(None)
    np.testing.assert_array_equal(state.agent_dir, [envs.SOUTH, envs.SOUTH])
    assert envs.make("two_rooms", start_dir=0).start_dir == envs.EAST
