"""The ``jaxusar`` command: a thin argparse front over the package (DESIGN.md, layer ``cli``).

Each subcommand is one ``add_<name>(subparsers)`` function that declares its arguments and sets
``run`` to the function doing the work; ``COMMANDS`` lists them. Bad user input (an unknown map, an
out-of-range override, an unwritable output folder) ends with one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
import warnings
from pathlib import Path

import numpy as np


class UsageError(Exception):
    """Bad input from the command line: reported in one line, exit status 2, no traceback."""


def make_env(args: argparse.Namespace, **overrides):
    """The env named by ``--map`` with the given overrides; bad values become a UsageError."""
    from jaxusar.config import check_map_path
    from jaxusar.envs import LayoutError, make

    overrides = {k: v for k, v in overrides.items() if v is not None}
    try:
        check_map_path(args.map)
        return make(args.map, **overrides)
    except (LayoutError, ValueError, TypeError) as err:
        raise UsageError(str(err)) from None


def output_dir(path: Path) -> Path:
    """Create ``path`` (and parents) for a command's files; failure is a UsageError."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(f"cannot create the output folder {str(path)!r}: {err.strerror or err}") from None
    return path


# -- demo -----------------------------------------------------------------------------------------
def add_demo(subparsers) -> None:
    from jaxusar.envs import available_layouts

    p = subparsers.add_parser(
        "demo", help="show a map, its region graph and the planner's optimum; play and draw an optimal episode",
        description="Print the map, its region graph, the lower bound on the team's steps and per-agent "
                    "distances; save DIR/map.png and DIR/episode.png. Where the exact joint search is in reach "
                    "(small maps such as two_rooms, three_rooms and two_rooms_rubble), also print the optimal team "
                    "steps and play one optimal joint plan (where victims are drawn at reset: for the draw of "
                    "--seed); elsewhere the episode is a uniformly random policy's, said so in one line.")
    p.add_argument("--map", default="two_rooms",
                   help=f"a shipped map ({', '.join(available_layouts())}) or a path to a .txt layout "
                        "(default: two_rooms)")
    p.add_argument("--out", type=Path, default=Path("runs/demo"), metavar="DIR",
                   help="folder for the pictures (default: runs/demo)")
    p.add_argument("--horizon", type=int, default=None, metavar="N",
                   help="episode step cap (default: the env's, 100)")
    p.add_argument("--seed", type=int, default=0, metavar="N",
                   help="the reset key (where the map draws its victims at reset) and the random policy's seed "
                        "(default: 0)")
    p.set_defaults(run=demo)


def region_lines(graph, victim_region: np.ndarray, agent_region: np.ndarray) -> list[str]:
    """The demo's region table, one line per region; its columns stay aligned past region 9."""
    index_width, name_width = len(str(graph.n_regions - 1)), max([14, *map(len, graph.names)])
    lines = []
    for r, (name, kind) in enumerate(zip(graph.names, graph.kinds)):
        victims, agents = np.flatnonzero(victim_region == r).tolist(), np.flatnonzero(agent_region == r).tolist()
        cells = int((graph.cell_region == r).sum())
        lines.append(f"  {r:>{index_width}}  {name:<{name_width}} {kind:<5} {cells:3d} cells   "
                     f"victims {str(victims):<8} agents at start {agents}")
    return lines


def demo(args: argparse.Namespace) -> int:
    import jax

    from jaxusar import planning
    from jaxusar.envs import ACTION_NAMES, DIRECTION_NAMES, ENGINEER
    from jaxusar.envs.render import (FOG_LEGEND, ROLE_WORDS, ascii_legend, render_ascii, reset_state,
                                     rollout_states, save_episode_strip, save_map)

    if args.seed < 0:
        raise UsageError(f"--seed must be >= 0, got {args.seed}")
    env = make_env(args, horizon=args.horizon)
    out = output_dir(args.out)  # before the work, so a bad --out fails fast
    key = jax.random.key(args.seed)
    print(repr(env))
    state = reset_state(env, key)
    drawn = f" (victims drawn with --seed {args.seed})" if env.n_drawn else ""
    print(f"\nReset state{drawn} ({ascii_legend(env, fog=False)}):")
    print(render_ascii(env, state, fog=False))
    if env.observation == "view":
        print(f"\nThe same, as the team has seen it (observation 'view': {FOG_LEGEND}):")
        print(render_ascii(env, state, fog=True))

    graph = env.graph
    starts = env.layout.agent_start
    names = [f"{ROLE_WORDS[int(role)]} {i}" for i, role in enumerate(env.roles)]
    victim_region = graph.cell_region[tuple(np.asarray(state.victim_pos).T)]
    print(f"\nRegion graph ({graph.n_regions} region{'s' if graph.n_regions != 1 else ''}):")
    print("\n".join(region_lines(graph, victim_region, graph.cell_region[tuple(starts.T)])))
    print("  edges: " + (", ".join(f"{a} -- {b}" for a, b in graph.edges()) or "(none)"))

    # the planner works on fixed victims: where they are drawn, on this reset's draw (a plan that knows it)
    fixed = planning.fixed_victims(env, np.asarray(state.victim_pos)) if env.n_drawn else env
    if env.n_drawn:
        print("\nVictims are drawn at reset: the planner below plans for this draw, knowing where they are.")
    start = time.perf_counter()
    try:
        lower = planning.team_lower_bound(fixed)
        print(f"\nLower bound on the team's steps (exact single-medic tours over victim assignments, collisions "
              f"ignored): {lower} ({time.perf_counter() - start:.2f} s)")
    except (planning.Unreachable, ValueError) as err:
        print(f"\nLower bound on the team's steps: none ({err})")
    plan, steps, why = None, None, None
    if not planning.in_reach(fixed):
        limit = planning.SEARCH_MAX_BOUND if fixed.part1 else planning.PRUNED_SEARCH_MAX_BOUND
        why = "the exact search is out of reach on this map"
        print(f"\nOptimal team steps: not searched; the exact joint BFS could visit up to "
              f"{planning.joint_states_bound(fixed):.2g} states on this map ({env.n_agents} agents, {env.n_victims} "
              f"victims; the exact search runs up to {limit:.0e})")
    else:
        start = time.perf_counter()
        try:
            if fixed.expires:  # "optimal" is the highest return where critical victims expire
                best = planning.optimal_team_return(fixed)
                plan, steps = best["plan"], best["steps"]
                print(f"\nHighest return from the reset state (exact joint search; critical victims expire at step "
                      f"{fixed.critical_expires}): {best['return']:g} in {steps} steps "
                      f"({time.perf_counter() - start:.1f} s)")
            else:
                plan = planning.optimal_team_plan(fixed)
                steps = len(plan)
                print(f"\nOptimal team steps from the reset state (exact joint BFS): {steps}")
        except (planning.Unreachable, MemoryError, ValueError) as err:  # SearchTooLarge is a MemoryError
            plan, why = None, f"the exact search found none: {err}"
            print(f"\nOptimal team steps: {why}")
    alone = "; -1: not alone, behind rubble" if env.has_rubble else ""
    print(f"Per-agent shortest steps, each agent alone on the map (to enter a region / to triage a victim{alone}):")
    for i, (r, c) in enumerate(starts):
        where = f"  {names[i]} at ({r}, {c}) facing {DIRECTION_NAMES[env.start_dir]}"
        if env.roles[i] == ENGINEER:
            print(f"{where}: an engineer (clears rubble, triages no one)")
            continue
        try:
            dist = planning.agent_distances(fixed, i)
        except (planning.Unreachable, MemoryError, ValueError) as err:
            print(f"{where}: not available ({err})")
            continue
        regions = "  ".join(f"{n}={d}" for n, d in zip(graph.names, dist["to_region"]))
        triage = "  ".join(f"victim {v}={d}" for v, d in enumerate(dist["to_triage"]))
        print(f"{where}: to_region {regions}; to_triage {triage}")

    if plan is not None:
        states, rewards = rollout_states(env, plan, key)
        played = len(rewards)
        kind = "highest-return" if fixed.expires else "optimal"
        print(f"\nOne {kind} joint plan ({len(plan)} steps), played through env.step:")
        print("   t  " + "".join(f"{n:<12}" for n in names) + "reward  triaged")
        for t in range(played):
            acts = "".join(f"{'CLEAR' if env.roles[i] == ENGINEER and a == 3 else ACTION_NAMES[a]:<12}"
                           for i, a in enumerate(plan[t]))
            print(f"  {t + 1:2d}  {acts}{rewards[t]:6g}  {np.asarray(states[t + 1].triaged).astype(int)}")
        title = f"{env.layout.name}: an {kind} joint plan, {played} of {steps} steps played"
    else:  # never a missing picture: a random team shows the map in motion
        actions = np.random.default_rng(args.seed).integers(0, 4, (env.horizon, env.n_agents), dtype=np.int32)
        states, rewards = rollout_states(env, actions, key)
        played = len(rewards)
        print(f"\nNo plan to show ({why}): playing a uniformly random policy instead (--seed {args.seed}).")
        title = f"{env.layout.name}: a uniformly random policy (no plan: {why}), {played} steps"
    final = states[-1]
    print("\nFinal state:")
    print(render_ascii(env, final, fog=False))
    triaged, dead = np.asarray(final.triaged), np.asarray(final.dead)
    if triaged.all():
        outcome = "all victims triaged"
    elif (triaged | dead).all():
        outcome = f"every victim triaged or dead: {int(dead.sum())} died"
    else:
        outcome = f"the horizon of {env.horizon} steps ended it first"
    print(f"Return {rewards.sum():g} in {played} steps ({outcome}).")

    written, failed = [], []
    for name, draw in (("map.png", lambda p: save_map(env, p, state=states[0])),
                       ("episode.png", lambda p: save_episode_strip(env, states, p, rewards=rewards,
                                                                    suptitle=f"{title}, return {rewards.sum():g}"))):
        try:
            written.append(draw(out / name))
        except (OSError, ValueError, RuntimeError) as err:
            failed.append(f"could not draw {out / name}: {err}")
    print("")
    for path in written:
        print(f"Wrote {path}")
    for line in failed:
        print(f"jaxusar demo: error: {line}", file=sys.stderr)
    return 1 if failed else 0


# -- train --------------------------------------------------------------------------------------
def add_train(subparsers) -> None:
    from jaxusar import algos

    try:
        listed = "\n".join(f"  {name:<13} {algos.describe(m)}" for name, m in algos.registry().items())
        figures = "".join(f"  {name:<13} {', '.join(f)}\n" for name, f in train_figures().items())
    except (algos.RegistryError, ImportError) as err:  # a broken learner file: the help still prints, `train` says why
        listed = f"  (cannot list them: {err})"
        figures = f"  (cannot list them: {err})\n"
    p = subparsers.add_parser(
        "train", help="train one algorithm's trials in one vmapped call and write its results folder",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Train N trials of ALGO at once (one jit(vmap) call per chunk) and write DIR/metrics.json, "
                    "DIR/curves.csv, DIR/params/ and the algorithm's figures:\n"
                    + figures
                    + "Settings: the algorithm's defaults, the map-derived ones (docs/algorithms.md), the map's settings "
                    "file if it has one, then --config "
                    "FILE, then --set overrides. A tiny run: --trials 2 --set train.episodes=100 (train.test_every "
                    "must not exceed train.episodes; hierarchical's budgets are per stage: train.episodes per "
                    "sub-policy, hierarchical.coordinator.episodes for the coordinator).",
        epilog=f"algorithms:\n{listed}\n\nA learner file in jaxusar/algos that sets ALGORITHM = \"NAME\" is "
               "listed here (docs/extending.md).\n")
    p.add_argument("algo", help="the algorithm to train (listed below)")
    p.add_argument("--trials", type=int, default=8, help="independent seeds, run side by side (default 8)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="results folder (default runs/ALGO-MAP, e.g. runs/iql-two_rooms)")
    p.add_argument("--config", type=Path, default=None, metavar="FILE", help="YAML config (see configs/)")
    p.add_argument("--map", default=None, metavar="NAME|PATH",
                   help="a shipped map or a path to a .txt layout (docs/maps.md); the same as "
                        "--set env.map=NAME (default: the config's, two_rooms)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="override one setting, e.g. --set train.episodes=500 (repeatable)")
    p.add_argument("--options", default=None, metavar="K[,K...]",
                   help="doc (option-critic) only: numbers of options per agent, one run each (paper: 2,4,8)")
    add_run_arguments(p)
    p.set_defaults(run=train)


def train_figures() -> dict[str, tuple[str, ...]]:
    """The figures ``jaxusar train ALGO`` writes, per listed algorithm (its experiment's FIGURES)."""
    from jaxusar import algos
    from jaxusar.experiments.train import experiment_class

    return {name: tuple(getattr(experiment_class(name), "FIGURES", ())) for name in algos.registry()}


def add_run_arguments(p) -> None:
    """What every training command takes: overwriting, checkpoints, progress."""
    p.add_argument("--force", action="store_true",
                   help="overwrite a finished run in DIR, or start an interrupted one over (default: resume it)")
    p.add_argument("--checkpoint-every", type=float, default=60.0, metavar="SECONDS",
                   help="seconds between checkpoints of the training state (default 60; 0: after every chunk)")
    p.add_argument("--quiet", action="store_true", help="no progress lines (the results are printed at the end)")
    p.add_argument("--no-compile-cache", action="store_true",
                   help="compile every program afresh (default: JAX's persistent compilation cache in "
                        "~/.cache/jaxusar/xla or $JAX_COMPILATION_CACHE_DIR, so a second run loads its programs; "
                        "JAXUSAR_COMPILE_CACHE=0 also turns it off)")


def check_run_arguments(args: argparse.Namespace) -> None:
    """Check what every training command takes, then turn on the compilation cache (before any compile)."""
    from jaxusar.experiments.usage import enable_compile_cache

    if args.checkpoint_every < 0:
        raise UsageError(f"--checkpoint-every must be >= 0 seconds, got {args.checkpoint_every:g}")
    if args.trials is not None and args.trials < 1:
        raise UsageError(f"--trials must be >= 1, got {args.trials}")
    enable_compile_cache(not args.no_compile_cache)


def parse_options(text: str | None) -> tuple[int, ...] | None:
    if text is None:
        return None
    try:
        ks = tuple(int(k) for k in text.split(","))
    except ValueError:
        raise UsageError(f"--options {text!r}: expected comma-separated integers, e.g. 2,4,8") from None
    if not ks or any(k < 1 for k in ks):
        raise UsageError(f"--options {text!r}: every number of options must be >= 1")
    return ks


def train(args: argparse.Namespace) -> int:
    from jaxusar import algos, config
    from jaxusar.core.checkpoint import CheckpointError
    from jaxusar.envs import LayoutError
    from jaxusar.experiments import train as experiment

    check_run_arguments(args)
    options = parse_options(args.options)
    if options is not None and args.algo != "doc":
        raise UsageError("--options applies to doc (option-critic) only")
    try:
        if args.map is not None:
            config.check_map_path(args.map, "--map: ")
        sets = ([f"env.map={json.dumps(args.map)}"] if args.map is not None else []) + args.sets
        cfg = config.load(args.config, sets, defaults=algos.defaults(args.algo))
        if cfg.algo != args.algo:
            raise config.ConfigError(f"the config is for algo {cfg.algo!r} but the command trains {args.algo!r}; "
                                     f"to start from that file's settings, add --set algo={args.algo}")
        extra = {} if options is None else {"options": options}
        experiment.run(cfg, args.trials, args.out, force=args.force, quiet=args.quiet,
                       checkpoint_every=args.checkpoint_every, command=args.command_line, **extra)
    except (config.ConfigError, LayoutError, FileExistsError, CheckpointError) as err:
        raise UsageError(str(err)) from None
    return 0


# -- reproduce ----------------------------------------------------------------------------------
def add_reproduce(subparsers) -> None:
    p = subparsers.add_parser(
        "reproduce", help="the paper's Table II and Figs. 4-6: every method, N trials each, in one command",
        description="Train the hierarchical method, option-critic (2, 4, 8 options) and IQL, N trials each in one "
                    "vmapped call per trainer, side by side, and play the scripted team (no learning); write "
                    "DIR/results.json, DIR/table2.md, the figures and one folder per algorithm. Where victims are "
                    "drawn at reset, every team is scored on the same 32 draws against the clairvoyant optimum "
                    "(normalized score). A method that cannot run on the map is left out, with why. Interrupted "
                    "runs resume from their checkpoints.")
    p.add_argument("--trials", type=int, default=8, help="independent seeds per algorithm (default 8, as the paper)")
    p.add_argument("--map", default=None, metavar="NAME|PATH",
                   help="a shipped map or a path to a .txt layout (docs/maps.md); default two_rooms")
    p.add_argument("--out", type=Path, default=None, metavar="DIR", help="results folder (default results/<map>)")
    p.add_argument("--quick", action="store_true",
                   help="reduced budgets: the same pipeline in minutes (about 4 on a 2-core CPU), for a first look")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="[ALGO.]KEY=VALUE",
                   help="override a setting of every algorithm (env.horizon=200) or of one "
                        "(iql.train.episodes=100); repeatable")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="trainers run side by side (default: one per CPU core)")
    p.add_argument("--distributed", action="store_true",
                   help="several processes or hosts: call jax.distributed.initialize() and split the trials "
                        "across the processes (docs/performance.md, 'Beyond one device'); without the three options below, "
                        "JAX detects the cluster itself (Slurm, Open MPI, TPU pods)")
    p.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="with --distributed: address of process 0, the same on every process")
    p.add_argument("--num-processes", type=int, default=None, metavar="N", help="with --distributed: processes in all")
    p.add_argument("--process-id", type=int, default=None, metavar="I", help="with --distributed: this process, 0..N-1")
    add_run_arguments(p)
    p.set_defaults(run=reproduce)


def start_distributed(args: argparse.Namespace) -> None:
    """Check the --distributed options (before anything waits on the network), then join the cluster."""
    cluster = {"--coordinator": args.coordinator, "--num-processes": args.num_processes,
               "--process-id": args.process_id}
    given = [k for k, v in cluster.items() if v is not None]
    if not args.distributed:
        if given:
            raise UsageError(f"{', '.join(given)} need --distributed")
        return
    n, i = args.num_processes, args.process_id
    if n is not None and n < 1:
        raise UsageError(f"--num-processes must be >= 1, got {n}")
    if n is not None and i is not None and not 0 <= i < n:
        raise UsageError(f"--process-id must be in 0..{n - 1}, got {i}")
    if n is not None and args.trials % n:
        raise UsageError(f"--trials {args.trials} cannot be split evenly over {n} processes")
    import jax

    jax.distributed.initialize(coordinator_address=args.coordinator, num_processes=n, process_id=i)


def reproduce(args: argparse.Namespace) -> int:
    from jaxusar import config
    from jaxusar.core.checkpoint import CheckpointError
    from jaxusar.envs import LayoutError
    from jaxusar.experiments import reproduce as experiment

    check_run_arguments(args)
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {args.workers}")
    start_distributed(args)
    try:
        if args.map is not None:
            config.check_map_path(args.map, "--map: ")
        experiment.run(args.trials, args.out, quick=args.quick, sets=args.sets, force=args.force, quiet=args.quiet,
                       checkpoint_every=args.checkpoint_every, workers=args.workers, command=args.command_line,
                       map=args.map)
    except (config.ConfigError, LayoutError, FileExistsError, CheckpointError) as err:
        raise UsageError(str(err)) from None
    return 0


# -- benchmark ----------------------------------------------------------------------------------
def add_benchmark(subparsers) -> None:
    p = subparsers.add_parser(
        "benchmark", help="sample-efficiency benchmark: every algorithm on a versioned task suite, rliable statistics",
        description="Train every algorithm on every task of the suite (versioned ids such as two_rooms-v1; --list "
                    "shows them), N trials each, all trainers side by side, the longest first; score each trial "
                    "against the task's reference (exact optimum, lower bound, or clairvoyant bound); write "
                    "DIR/leaderboard.md, DIR/tasks.md, DIR/results.json and four figures. Interrupted runs resume.")
    p.add_argument("--tasks", nargs="+", default=None, metavar="ID", help="task ids (default: every task)")
    p.add_argument("--algorithms", nargs="+", default=None, metavar="ALGO",
                   help="hierarchical, doc, iql, vdn, qmix, scripted (default: all)")
    p.add_argument("--trials", type=int, default=None,
                   help="independent seeds per task and algorithm (default 8; 2 with --quick)")
    p.add_argument("--quick", action="store_true",
                   help="reduced budgets and 2 trials, no per-run figures: the whole suite in minutes, for a "
                        "first look")
    p.add_argument("--out", type=Path, default=None, metavar="DIR", help="results folder (default results/benchmark)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="[ALGO.]KEY=VALUE",
                   help="override a setting of every algorithm or of one (iql.train.episodes=100); repeatable")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="trainers run side by side (default: one per CPU core)")
    p.add_argument("--list", action="store_true", help="list the tasks and exit")
    add_run_arguments(p)
    p.set_defaults(run=benchmark)


def benchmark(args: argparse.Namespace) -> int:
    from jaxusar import config
    from jaxusar.core.checkpoint import CheckpointError
    from jaxusar.envs import LayoutError
    from jaxusar.experiments import benchmark as experiment
    from jaxusar.experiments.suite import TASKS

    if args.list:
        width = max(map(len, TASKS))
        for task_id, task in TASKS.items():
            print(f"{task_id:<{width}}  {task.describe()}")
        return 0
    check_run_arguments(args)
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {args.workers}")
    try:
        experiment.run(args.tasks, args.algorithms, args.trials, args.out, quick=args.quick, sets=args.sets,
                       force=args.force, quiet=args.quiet, checkpoint_every=args.checkpoint_every,
                       workers=args.workers, command=args.command_line)
    except (config.ConfigError, LayoutError, FileExistsError, CheckpointError) as err:
        raise UsageError(str(err)) from None
    return 0


# -- maps ---------------------------------------------------------------------------------------
def add_maps(subparsers) -> None:
    p = subparsers.add_parser("maps", help="generate rooms-and-corridors maps; segment a layout into regions",
                              description="Map tools. A written map runs with --set env.map=DIR/NAME.txt.")
    sub = p.add_subparsers(dest="maps_command", required=True, metavar="ACTION")
    g = sub.add_parser("generate", help="a seeded rooms-and-corridors map: NAME.txt, NAME.regions.txt, NAME.png",
                       description="Write a rooms-and-corridors map (1-wide corridors, one doorway per room), "
                                   "its region grid (segmented from the layout) and a picture. The same "
                                   "arguments give the same map; every victim is checked reachable.")
    for name, default, text in (("height", 20, "rows"), ("width", 30, "columns"), ("rooms", 8, "rooms"),
                                ("medics", 4, "medics (agents), started in corridors"),
                                ("victims", 6, "victims, in distinct rooms while rooms last"), ("seed", 0, "seed")):
        g.add_argument(f"--{name}", type=int, default=default, help=f"{text} (default: {default})")
    add_map_features(g)
    g.add_argument("--name", default=None, help="file name stem (default: rooms<R>_<H>x<W>_s<SEED>)")
    add_hall_radius(g)
    g.add_argument("--out", type=Path, default=Path("runs/maps"), metavar="DIR", help="folder (default: runs/maps)")
    g.set_defaults(run=maps_generate)
    s = sub.add_parser("segment", help="write the region grid segmented from a layout beside it (NAME.regions.txt)",
                       description="Segment a .txt layout into rooms and halls (doorways split regions) and write "
                                   "NAME.regions.txt beside it, unless one exists (--force replaces it).")
    s.add_argument("layout", type=Path, help="a .txt layout")
    s.add_argument("--force", action="store_true", help="replace an existing region grid")
    add_hall_radius(s)
    s.set_defaults(run=maps_segment)


def add_hall_radius(parser) -> None:
    from jaxusar.envs.mapgen import HALL_RADIUS

    def radius(text: str) -> int:
        if not text.isdigit():
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of steps (0 keeps halls whole)")
        return int(text)

    parser.add_argument("--hall-radius", type=radius, default=HALL_RADIUS, metavar="STEPS",
                        help="cut halls into pieces within STEPS steps of a piece's centre, so that no "
                             f"navigation sub-policy crosses a whole corridor; 0 keeps them whole (default: {HALL_RADIUS})")


MAP_SETTINGS = (("triage-steps", int, "TRIAGE actions a regular victim needs (default: 1)"),
                ("critical-triage-steps", int, "TRIAGE actions a critical victim needs (default: 1)"),
                ("critical-reward", float, "reward for triaging a critical victim (default: 300)"),
                ("critical-expires", int, "the step at which untriaged critical victims die (default: never)"),
                ("view-radius", int, "cells (Chebyshev) an agent sees within its region (default: the whole region)"),
                ("observation", str, "full or view (partial observability; default: full)"))


def add_map_features(g) -> None:
    """``maps generate``'s contract-part-2 options: mapgen.generate's keyword arguments and header settings."""
    from jaxusar.envs.mapgen import DRAW_CELLS

    for name, text in (("engineers", "engineers ('E'), started in corridors"),
                       ("rubble", "room doorways under rubble ('r'); needs --engineers"),
                       ("critical", "how many of the --victims are critical ('C')"),
                       ("random-regular", "regular victims drawn at every reset over the '?' cells"),
                       ("random-critical", "critical victims drawn at every reset over the '?' cells")):
        g.add_argument(f"--{name}", type=int, default=0, metavar="N", help=f"{text} (default: 0)")
    g.add_argument("--draw-cells", type=int, default=DRAW_CELLS, metavar="N",
                   help="with --random-*: '?' cells per room at most, where victims may be drawn "
                        f"(default: {DRAW_CELLS})")
    for name, kind, text in MAP_SETTINGS:
        g.add_argument(f"--{name}", type=kind, default=None, metavar="N" if kind is not str else "full|view",
                       help=f"a header line of the map: {text}")


def map_features(args: argparse.Namespace) -> dict:
    """``mapgen.generate``'s keyword arguments from ``maps generate``'s options."""
    settings = {name.replace("-", "_"): getattr(args, name.replace("-", "_")) for name, _, _ in MAP_SETTINGS}
    return dict(engineers=args.engineers, rubble=args.rubble, critical=args.critical,
                random_regular=args.random_regular, random_critical=args.random_critical, draw_cells=args.draw_cells,
                settings={k: v for k, v in settings.items() if v is not None} or None)


def maps_generate(args: argparse.Namespace) -> int:
    from jaxusar.envs import ENGINEER, MEDIC, USAREnv
    from jaxusar.envs.mapgen import GeneratorError, generated_layout
    from jaxusar.envs.render import save_map

    name = args.name or f"rooms{args.rooms}_{args.height}x{args.width}_s{args.seed}"
    start = time.perf_counter()
    try:  # numpy only: bad arguments end here, before anything compiles
        layout, text, regions = generated_layout(args.height, args.width, args.rooms, args.medics, args.victims,
                                                 args.seed, name=name, hall_radius=args.hall_radius,
                                                 **map_features(args))
    except GeneratorError as err:
        raise UsageError(str(err)) from None
    seconds = time.perf_counter() - start
    out = output_dir(args.out)
    (out / f"{name}.txt").write_text(text)
    (out / f"{name}.regions.txt").write_text(regions)
    png = save_map(USAREnv(layout), out / f"{name}.png")
    print(layout.to_ascii())
    header = [line for line in text.split("---\n")[0].splitlines() if not line.startswith(";")]
    if header:
        print("header: " + "; ".join(header))
    engineers, critical = int((layout.roles == ENGINEER).sum()), int(layout.victim_kind.sum())
    drawn = sum(layout.header.get("random_victims", (0, 0)))
    rubble = int(layout.rubble.sum())
    parts = [f"{layout.shape[0]}x{layout.shape[1]}", f"{len(layout.region_names)} regions "
             f"({sum(k == 'room' for k in layout.region_kinds)} rooms)", f"{int((layout.roles == MEDIC).sum())} medics"]
    parts += [f"{engineers} engineer{'s' * (engineers != 1)}"] if engineers else []
    parts += [f"{len(layout.victim_pos)} victims" + (f" ({critical} critical)" if critical else "")]
    parts += [f"{drawn} drawn at reset over {len(layout.random_cells)} '?' cells"] if drawn else []
    parts += [f"{rubble} doorway{'s' * (rubble != 1)} under rubble"] if rubble else []
    print(", ".join(parts) + f"; generated, segmented and checked in {seconds * 1000:.0f} ms")
    print(f"Wrote {out / f'{name}.txt'}, {out / f'{name}.regions.txt'} and {png}; "
          f"train on it with --set env.map={out / f'{name}.txt'}")
    return 0


def maps_segment(args: argparse.Namespace) -> int:
    from jaxusar.envs import LayoutError, parse_layout
    from jaxusar.envs.layout import companion
    from jaxusar.envs.mapgen import segmented_regions_text

    if args.layout.suffix != ".txt" or not args.layout.is_file():
        raise UsageError(f"{str(args.layout)!r} is not a .txt layout file")
    target = companion(args.layout, ".regions.txt")
    if target.exists() and not args.force:
        raise UsageError(f"{target} exists (a hand-made region grid wins); --force replaces it")
    text = args.layout.read_text()
    try:
        regions = segmented_regions_text(text, args.layout.stem, args.hall_radius)
        layout = parse_layout(text, regions, name=args.layout.stem)
    except LayoutError as err:
        raise UsageError(str(err)) from None
    target.write_text(regions)
    print(regions.split("---\n", 1)[1], end="")
    print(f"{len(layout.region_names)} regions: " + ", ".join(f"{n} ({k})" for n, k in
                                                              zip(layout.region_names, layout.region_kinds)))
    print(f"Wrote {target}")
    return 0


# -- entry point ----------------------------------------------------------------------------------
COMMANDS = (add_demo, add_train, add_reproduce, add_benchmark, add_maps)
INTERRUPTED = 130  # the exit status of a command ended by Ctrl-C (128 + SIGINT), as shells report it


def build_parser() -> argparse.ArgumentParser:
    from jaxusar import __version__

    parser = argparse.ArgumentParser(
        prog="jaxusar", description="Multi-agent hierarchical RL in urban search and rescue, in JAX.")
    parser.add_argument("--version", action="version", version=f"jaxusar {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in COMMANDS:
        add(subparsers)
    return parser


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"jaxusar: warning: {message}", file=sys.stderr if file is None else file)


def main(argv: list[str] | None = None) -> int:
    """Run ``jaxusar COMMAND ...``; returns the exit status (bad input raises SystemExit(2))."""
    argv = sys.argv[1:] if argv is None else list(argv)
    warnings.showwarning = _one_line_warning
    args = build_parser().parse_args(argv)
    args.command_line = "jaxusar " + shlex.join(argv)  # recorded in metrics.json / results.json
    try:
        return args.run(args)
    except BrokenPipeError:  # output piped into `head` and the like: stop quietly
        sys.stderr.close()
        return 0
    except UsageError as err:
        print(f"jaxusar {args.command}: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    except KeyboardInterrupt as err:  # Ctrl-C: one line, not a traceback (runner.Interrupted says where to resume)
        print(f"jaxusar {args.command}: {str(err) or 'interrupted'}", file=sys.stderr, flush=True)
        if getattr(err, "abandoned_threads", False):  # trainers still in their chunk: do not wait for them
            sys.stdout.flush()
            os._exit(INTERRUPTED)
        return INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
