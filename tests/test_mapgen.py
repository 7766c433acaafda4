"""Maps without hand work: segmentation into regions, the seeded generator, ``jaxusar maps``."""

from __future__ import annotations

import numpy as np
import pytest

import hashlib

from jaxusar import envs
from jaxusar.cli import main
from jaxusar.envs import LayoutError, layout as layout_module, mapgen
from jaxusar.envs.layout import parse_layout

ROOMS_AND_HALL = """\
V...#.....#....
....#.....#...V
....#..V..#....
....#.....#....
##.####.####.##
...............
A.............A"""


def blocked(grid: str) -> np.ndarray:
    chars = np.array([list(row) for row in grid.splitlines()])
    return (chars == "#") | (chars == "X")


def test_doorways_split_rooms_from_the_hall():
    region, names, kinds = mapgen.segment(blocked(ROOMS_AND_HALL), hall_radius=0)
    assert names == ("room_0", "room_1", "room_2", "hall_0") and kinds == ("room",) * 3 + ("hall",)
    np.testing.assert_array_equal(region[0], [0, 0, 0, 0, -1, 1, 1, 1, 1, 1, -1, 2, 2, 2, 2])
    assert region[4, 2] == region[4, 7] == region[4, 12] == 3  # the doorways belong to the hall
    assert (region[5:] == 3).all() and (region[:4, :4] == 0).all()


def _within(piece: np.ndarray, radius: int) -> bool:
    """Whether some cell of ``piece`` reaches all of it within ``radius`` steps, staying inside it."""
    return any(mapgen._geodesic(piece, [tuple(c)])[0][piece].max() <= radius for c in np.argwhere(piece))


@pytest.mark.parametrize("radius", [1, 2, 4, 6])
def test_a_long_hall_is_cut_into_connected_pieces_of_the_radius(radius):
    whole, _, _ = mapgen.segment(blocked(ROOMS_AND_HALL), hall_radius=0)
    region, names, kinds = mapgen.segment(blocked(ROOMS_AND_HALL), hall_radius=radius)
    np.testing.assert_array_equal(region[whole < 3], whole[whole < 3])  # the rooms are untouched
    pieces = [region == k for k in range(len(names)) if kinds[k] == "hall"]
    assert np.array_equal(np.logical_or.reduce(pieces), whole == 3)  # the hall, every cell in one piece
    assert len(pieces) > 1  # 33 cells, 16 steps end to end: more than one piece at any of these radii
    for piece in pieces:
        assert mapgen._components(piece)[1] == 1 and _within(piece, radius)
    assert names[3:] == tuple(f"hall_{k}" for k in range(len(pieces)))


def test_a_hall_within_the_radius_stays_whole():
    region, names, kinds = mapgen.segment(blocked(ROOMS_AND_HALL), hall_radius=16)
    np.testing.assert_array_equal(region, mapgen.segment(blocked(ROOMS_AND_HALL), hall_radius=0)[0])


def test_a_big_map_cuts_its_halls_coarser_rather_than_outgrow_a_region_file():
    """80x80 with 40 rooms: radius-4 pieces would be 96 regions, more than a region file's 62 letters; the
    radius doubles until they fit (16 here), and the written file says so."""
    layout, _, regions = mapgen.generated_layout(80, 80, 40, 4, 6, 0)
    assert 41 < len(layout.region_names) <= len(mapgen.LETTERS)
    assert "hall_radius=16)" in regions.splitlines()[0]
    assert "hall_radius=4)" in mapgen.generated_layout(40, 40, 12, 4, 6, 0)[2].splitlines()[0]


def test_pockets_join_their_room_and_a_door_between_two_rooms_joins_one():
    grid = """\
.....#....
.....#....
..........
.....#....
####.#....
....#.....
....#....."""
    region, names, kinds = mapgen.segment(blocked(grid))
    # rooms: left-top block (rows 0-3, cols 0-4), the right block (cols 6-9), the bottom-left block is too
    # narrow below row 4 (4 wide, 2 tall): a thin area that touches two rooms, so it stays a hall
    assert kinds.count("room") == 2
    assert region[2, 5] in (region[2, 4], region[2, 6])  # the 1-cell doorway between two rooms joined one
    assert kinds[region[5, 0]] == "hall"


def test_a_map_without_region_file_is_segmented_and_written(tmp_path):
    (tmp_path / "mine.txt").write_text(ROOMS_AND_HALL)
    with pytest.warns(UserWarning, match="segmented it from the layout.*room_0 \\(room\\).*wrote"):
        layout = envs.load_layout(str(tmp_path / "mine.txt"))
    written = (tmp_path / "mine.regions.txt").read_text()
    assert layout.region_names[:4] == ("room_0", "room_1", "room_2", "hall_0")  # the hall, cut into pieces
    region, names, _ = mapgen.segment(blocked(ROOMS_AND_HALL))
    np.testing.assert_array_equal(layout.region, region)
    # a person writes their own (the whole hall, then split in two their way): the file now wins
    written = mapgen.regions_text(*mapgen.segment(blocked(ROOMS_AND_HALL), hall_radius=0))
    edited = written.replace("D hall_0 hall", "D hall_0 hall\nE east_hall hall")
    lines = edited.split("---\n")
    rows = lines[1].splitlines()
    rows[5], rows[6] = rows[5][:8] + "E" * 7, rows[6][:8] + "E" * 7
    (tmp_path / "mine.regions.txt").write_text(lines[0] + "---\n" + "\n".join(rows) + "\n")
    again = envs.load_layout(str(tmp_path / "mine.txt"))
    assert again.region_names[-1] == "east_hall" and again.region[6, 14] == 4


def test_an_unwritable_region_file_is_a_warning_and_the_map_still_loads(tmp_path, monkeypatch):
    (tmp_path / "mine.txt").write_text(ROOMS_AND_HALL)
    def refuse(self, *a, **k):
        raise PermissionError(13, "Permission denied")
    monkeypatch.setattr("pathlib.Path.write_text", refuse)
    with pytest.warns(UserWarning, match="could not write .*mine.regions.txt.*Permission denied"):
        layout = envs.load_layout(str(tmp_path / "mine.txt"))
    assert layout.region_names == mapgen.segment(blocked(ROOMS_AND_HALL))[1]
    assert not (tmp_path / "mine.regions.txt").exists()


def test_a_layout_with_an_unreachable_victim_fails_before_anything_is_written(tmp_path):
    (tmp_path / "walled.txt").write_text("A..#V\n...#.")
    with pytest.raises(LayoutError, match="victim 0 at \\(0, 4\\) cannot be reached"):
        envs.load_layout(str(tmp_path / "walled.txt"))
    assert not (tmp_path / "walled.regions.txt").exists()


@pytest.mark.parametrize("name, medics, victims, rooms", [
    ("three_rooms", 2, 3, 3), ("four_rooms", 3, 4, 4), ("office", 4, 6, 9)])
def test_shipped_maps(name, medics, victims, rooms):
    env = envs.make(name)
    assert env.n_agents == medics and env.n_victims == victims
    assert env.graph.kinds.count("room") == rooms and "hall" in env.graph.kinds
    # the shipped region grids are what segmentation gives (none was edited by hand); three_rooms' and
    # four_rooms' were segmented before halls were cut into pieces, and keep their whole corridor
    region, names, kinds = mapgen.segment(env.layout.blocked, **({} if name == "office" else {"hall_radius": 0}))
    np.testing.assert_array_equal(region, env.layout.region)
    assert (names, kinds) == (env.layout.region_names, env.layout.region_kinds)
    if name == "office":
        assert env.layout.shape[0] >= 20 and env.layout.shape[1] >= 30


@pytest.mark.parametrize("seed", [0, 1, 7])
@pytest.mark.parametrize("height, width, rooms, medics, victims", [(40, 40, 12, 4, 8), (12, 20, 4, 2, 5),
                                                                   (22, 32, 9, 4, 6)])
def test_generated_maps_are_what_was_asked_and_reproducible(seed, height, width, rooms, medics, victims):
    layout, text, regions = mapgen.generated_layout(height, width, rooms, medics, victims, seed)
    assert layout.shape == (height, width)
    assert len(layout.agent_start) == medics and len(layout.victim_pos) == victims
    assert layout.region_kinds.count("room") == rooms and layout.region_kinds.count("hall") >= 1
    graph = envs.make(layout).graph
    halls = [k for k, kind in enumerate(graph.kinds) if kind == "hall"]
    assert all(graph.adjacency[r, halls].any() for r in graph.rooms)  # every room opens on a corridor piece
    assert all(graph.kinds[graph.cell_region[r, c]] == "hall" for r, c in layout.agent_start)
    rooms_with = {int(graph.victim_region[v]) for v in range(victims)}
    assert len(rooms_with) == min(victims, rooms)  # victims spread over distinct rooms while rooms last
    assert mapgen.generated_layout(height, width, rooms, medics, victims, seed)[1] == text
    assert mapgen.generate(height, width, rooms, medics, victims, seed + 100) != text
    parse_layout(text, regions)  # the written pair loads


@pytest.mark.parametrize("kwargs, message", [
    (dict(height=20, width=30, rooms=29, medics=2, victims=2), "29 rooms do not fit in a 20x30 map \\(at most 28"),
    (dict(height=20, width=30, rooms=4, medics=0, victims=2), "medics=0: must be an integer >= 1"),
    (dict(height=4, width=30, rooms=1, medics=1, victims=1), "height=4"),
    (dict(height=20, width=30, rooms=4, medics=2, victims=2, seed=-1), "seed=-1"),
])
def test_generator_bad_input(kwargs, message):
    with pytest.raises(mapgen.GeneratorError, match=message):
        mapgen.generate(**kwargs)


# generate's text for these arguments before contract part 2's features were added: they must not change
PART1_TEXTS = {
    (22, 32, 9, 4, 6, 0): "b3698857580b210e7521f9a78be546352425419f82e27115a0728574e9e9d5c5",
    (20, 30, 8, 4, 6, 3): "6b7a9418a873cdc182440dbad3b58d3ca9565ab7b71863618d7027b91d2b0d8d",
    (40, 40, 12, 4, 8, 1): "b7c569bc95a242ad56ee0ca11ba6065f88c2cc7483760edc54b9b47d9913decd",
    (12, 20, 4, 2, 5, 7): "9b62eb49a2529ff1dd41f47ecb89650c9d74b0bcd1873ddc9578b14090f781ec",
}


@pytest.mark.parametrize("args", list(PART1_TEXTS))
def test_default_features_reproduce_the_maps_generated_before_them(args):
    text = mapgen.generate(*args)
    assert hashlib.sha256(text.encode()).hexdigest() == PART1_TEXTS[args]
    # zero features spelled out change nothing either (draw_cells only matters with drawn victims)
    assert mapgen.generate(*args, engineers=0, rubble=0, critical=0, random_regular=0, random_critical=0,
                           draw_cells=5, settings={}) == text


def test_office_is_still_what_the_generator_makes():
    office = (layout_module.LAYOUT_DIR / "office.txt").read_text().split("---\n", 1)[1]
    assert mapgen.generate(height=22, width=32, rooms=9, medics=4, victims=6, seed=0).split("---\n", 1)[1] == office


PART2 = dict(engineers=2, rubble=3, critical=2, random_regular=3, random_critical=2, draw_cells=2,
             settings={"critical_expires": 80, "view_radius": 2, "critical_triage_steps": 2, "observation": "view"})


@pytest.mark.parametrize("seed", [0, 5])
def test_generated_part2_maps_are_what_was_asked_and_reproducible(seed):
    layout, text, regions = mapgen.generated_layout(22, 32, 9, 4, 6, seed, **PART2)
    assert mapgen.generated_layout(22, 32, 9, 4, 6, seed, **PART2)[1] == text
    plain, plain_text, plain_regions = mapgen.generated_layout(22, 32, 9, 4, 6, seed)
    # the features are drawn after the part-1 map: walls, rooms, doorways, medics and victim cells are kept
    np.testing.assert_array_equal(layout.blocked, plain.blocked)
    np.testing.assert_array_equal(layout.victim_pos, plain.victim_pos)
    assert set(map(tuple, plain.agent_start)) <= set(map(tuple, layout.agent_start))
    assert regions.split("---\n")[1] == plain_regions.split("---\n")[1]  # rubble and '?' segment as floor
    assert (layout.roles == envs.ENGINEER).sum() == 2 and (layout.roles == envs.MEDIC).sum() == 4
    assert layout.victim_kind.sum() == 2 and layout.rubble.sum() == 3
    graph = envs.make(layout).graph
    for r, c in np.argwhere(layout.rubble):  # in a doorway: walls on two opposite sides, a room and a corridor
        assert layout.wall[r, c - 1] and layout.wall[r, c + 1]
        assert {graph.kinds[graph.cell_region[r - 1, c]], graph.kinds[graph.cell_region[r + 1, c]]} == {"room", "hall"}
    assert all(graph.kinds[graph.cell_region[r, c]] == "hall" for r, c in layout.agent_start)
    cells = layout.random_cells
    assert len(cells) >= 5
    per_room = np.bincount(graph.cell_region[tuple(cells.T)], minlength=graph.n_regions)
    assert per_room.max() <= 2 and all(graph.kinds[k] == "room" for k in np.flatnonzero(per_room))
    grid = np.array([list(row) for row in text.split("---\n")[1].splitlines()])
    for r, c in cells:  # floor all around: no draw can wall a cell in
        ring = grid[r - 1:r + 2, c - 1:c + 2].copy()
        ring[1, 1] = "."
        assert (ring == ".").all()
    header = text.split("---\n")[0]
    for line in ("random_victims: 3 2", "critical_triage_steps: 2", "critical_expires: 80", "view_radius: 2",
                 "observation: view"):
        assert line + "\n" in header
    env = envs.make(layout)
    settings = (env.n_victims, env.n_drawn, env.critical_expires, env.view_radius, env.observation)
    assert settings == (11, 5, 80, 2, "view")
    assert env.victim_kind.tolist() == [int(k) for k in layout.victim_kind] + [0, 0, 0, 1, 1]


def test_every_draw_of_a_generated_map_leaves_every_victim_triageable():
    import jax

    layout, _, _ = mapgen.generated_layout(20, 30, 8, 3, 4, 2, engineers=1, rubble=8, random_regular=6,
                                           random_critical=4, draw_cells=3)
    env = envs.make(layout)
    starts = [tuple(cell) for cell in layout.agent_start[layout.roles == envs.MEDIC]]
    for key in jax.random.split(jax.random.key(0), 16):
        state = env.initial_state(key)
        open_ = ~layout.blocked  # every rubble cleared, every victim (fixed and drawn) in the way
        open_[tuple(np.asarray(state.victim_pos).T)] = False
        reach = layout_module._geodesic(open_, starts)[0] >= 0
        near = layout_module._neighbours(reach)
        assert all(near[r, c] for r, c in np.asarray(state.victim_pos))


@pytest.mark.parametrize("kwargs, message", [
    (dict(rubble=1), "rubble=1 needs engineers >= 1"),
    (dict(engineers=1, rubble=10), "rubble=10: only 9 doorways"),
    (dict(critical=7), "critical=7: more than the 6 fixed victims"),
    (dict(random_regular=40, draw_cells=1), "40 victims drawn at reset need as many '\\?' cells"),
    (dict(random_regular=1, draw_cells=0), "draw_cells=0: must be an integer >= 1"),
    (dict(engineers=-1), "engineers=-1: must be an integer >= 0"),
    (dict(settings={"random_victims": "1 0"}), "setting 'random_victims': unknown"),
    (dict(settings={"observation": "fog"}), "observation='fog': expected one of full, view"),
    (dict(settings={"critical_expires": 0}), "critical_expires=0: expected an integer >= 1"),
])
def test_generator_bad_part2_input(kwargs, message):
    with pytest.raises(mapgen.GeneratorError, match=message):
        mapgen.generate(22, 32, 9, 4, 6, 0, **kwargs)


def test_victims_may_all_be_drawn_but_a_map_needs_one():
    layout, _, _ = mapgen.generated_layout(20, 30, 8, 2, 0, 1, random_regular=2)
    assert len(layout.victim_pos) == 0 and layout.header["random_victims"] == (2, 0)
    with pytest.raises(mapgen.GeneratorError, match="victims=0"):
        mapgen.generate(20, 30, 8, 2, 0, 1)


def test_rubble_and_draw_cells_segment_as_floor():
    rows = [list(row) for row in ROOMS_AND_HALL.splitlines()]
    for r, c in ((1, 2), (2, 8), (3, 12)):
        rows[r][c] = "?"
    rows[4][2] = rows[4][7] = "r"  # two doorways under rubble
    rows[6][7] = "E"
    text = "random_victims: 2 0\n---\n" + "\n".join("".join(row) for row in rows)
    plain = "\n".join("".join("." if ch in "?rE" else ch for ch in row) for row in rows)
    assert mapgen.segmented_regions_text(text, "x") == mapgen.segmented_regions_text(plain, "x")
    layout = parse_layout(text, mapgen.segmented_regions_text(text, "x"))
    assert layout.rubble.sum() == 2 and len(layout.random_cells) == 3


def test_one_neighbour_function_for_layouts_and_segmentation():
    assert mapgen._neighbours is layout_module._neighbours
    assert "near[1:] |=" not in (layout_module.LAYOUT_DIR.parent / "mapgen.py").read_text()


def test_maps_generate_cli(tmp_path, capsys):
    out = tmp_path / "maps"
    assert main(["maps", "generate", "--height", "20", "--width", "30", "--rooms", "8", "--medics", "4",
                 "--victims", "6", "--seed", "3", "--out", str(out)]) == 0
    stem = "rooms8_20x30_s3"
    assert (out / f"{stem}.png").read_bytes()[:4] == b"\x89PNG"
    env = envs.make(str(out / f"{stem}.txt"))  # loads with its written region grid
    assert env.n_agents == 4 and env.graph.kinds.count("room") == 8
    assert "17 regions (8 rooms), 4 medics, 6 victims; generated, segmented and checked in" in capsys.readouterr().out
    assert main(["maps", "generate", "--height", "20", "--width", "30", "--rooms", "8", "--seed", "3", "--hall-radius",
                 "0", "--name", "whole", "--out", str(out)]) == 0
    assert "9 regions (8 rooms)" in capsys.readouterr().out  # one corridor, kept whole
    with pytest.raises(SystemExit) as e:
        main(["maps", "generate", "--rooms", "100", "--out", str(out)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and "100 rooms do not fit" in err


def test_maps_generate_cli_part2(tmp_path, capsys):
    out = tmp_path / "maps"
    assert main(["maps", "generate", "--rooms", "8", "--seed", "3", "--engineers", "1", "--rubble", "2", "--critical",
                 "1", "--random-regular", "2", "--random-critical", "1", "--draw-cells", "2", "--critical-expires",
                 "80", "--view-radius", "2", "--observation", "view", "--critical-triage-steps", "2",
                 "--name", "p2", "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert ("4 medics, 1 engineer, 6 victims (1 critical), 3 drawn at reset over" in stdout
            and "'?' cells, 2 doorways under rubble; generated" in stdout)
    assert "header: random_victims: 2 1; critical_triage_steps: 2; critical_expires: 80; view_radius: 2; " \
           "observation: view" in stdout
    env = envs.make(str(out / "p2.txt"))
    assert (env.n_agents, env.n_victims, env.critical_expires, env.observation) == (5, 9, 80, "view")
    assert (out / "p2.png").read_bytes()[:4] == b"\x89PNG"
    same = mapgen.generate(20, 30, 8, 4, 6, 3, engineers=1, rubble=2, critical=1, random_regular=2, random_critical=1,
                           draw_cells=2, settings={"critical_triage_steps": 2, "critical_expires": 80,
                                                   "view_radius": 2, "observation": "view"})
    assert (out / "p2.txt").read_text().split("---\n")[1] == same.split("---\n")[1]


@pytest.mark.parametrize("argv, message", [
    (["--rubble", "1"], "rubble=1 needs engineers >= 1 to clear it"),
    (["--critical", "9"], "critical=9: more than the 6 fixed victims"),
    (["--observation", "fog"], "observation='fog': expected one of full, view"),
    (["--random-regular", "99"], "99 victims drawn at reset need as many"),
    (["--view-radius", "-1"], "view_radius=-1: expected an integer >= 0"),
])
def test_maps_generate_cli_bad_part2_input_is_one_line_before_any_work(argv, message, tmp_path, capsys, monkeypatch):
    def no_env(*args, **kwargs):
        raise AssertionError("an env was built (and compiled) before the arguments were checked")
    monkeypatch.setattr(envs, "USAREnv", no_env)
    out = tmp_path / "maps"
    with pytest.raises(SystemExit) as e:
        main(["maps", "generate", "--out", str(out)] + argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and message in err and "Traceback" not in err
    assert not out.exists()


def test_maps_segment_cli(tmp_path, capsys):
    (tmp_path / "mine.txt").write_text(ROOMS_AND_HALL)
    assert main(["maps", "segment", str(tmp_path / "mine.txt"), "--hall-radius", "0"]) == 0
    assert "4 regions: room_0 (room), room_1 (room), room_2 (room), hall_0 (hall)" in capsys.readouterr().out
    for bad in ("-1", "two"):
        with pytest.raises(SystemExit) as e:
            main(["maps", "segment", str(tmp_path / "mine.txt"), "--force", "--hall-radius", bad])
        assert e.value.code == 2 and f"{bad!r} is not a whole number of steps" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # never overwrites a (maybe hand-made) region grid
        main(["maps", "segment", str(tmp_path / "mine.txt")])
    assert e.value.code == 2 and "--force" in capsys.readouterr().err
    assert main(["maps", "segment", str(tmp_path / "mine.txt"), "--force"]) == 0


def test_demo_on_a_map_too_big_for_the_exact_search(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--map", "four_rooms", "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "Optimal team steps: not searched; the exact joint BFS could visit up to" in stdout
    assert "Lower bound on the team's steps (exact single-medic tours" in stdout
    assert "room_0 -- hall_0" in stdout and (out / "map.png").read_bytes()[:4] == b"\x89PNG"
    # the promised episode is still drawn: a random policy's, said so in one line
    assert "No plan to show (the exact search is out of reach on this map): playing a uniformly random policy" in stdout
    assert (out / "episode.png").read_bytes()[:4] == b"\x89PNG" and f"Wrote {out / 'episode.png'}" in stdout


def test_training_where_the_exact_optimum_is_out_of_reach_measures_against_the_lower_bound():
    """four_rooms (3.2e9 joint states): the trainers' reference is the lower bound, found in a second."""
    from jaxusar import algos, config
    from jaxusar.experiments import train

    env, reference, _, trainer = train.build(config.load(None, ["env.map=four_rooms"], defaults=algos.defaults("iql")))
    assert reference == {"steps": 25, "reference": "lower bound", "lower_bound": 25}
    assert trainer.optimal_steps == 25 and env.n_agents == 3
