"""Where the exact joint search (``planning.optimal_team_steps``) stops being practical: states, seconds, memory.

Each case runs in its own process (so its peak RSS is its own) under a wall-clock limit, with the
search's size guard lifted (``max_states`` 60M); beside it, the lower bound's seconds
(``planning.team_lower_bound``), which replaces the optimum where the search is out of reach.

    python benchmarks/planner_limits.py            # writes benchmarks/results/planner_limits.json

Cases: the shipped maps, and generated maps (``mapgen.generated_layout``, seed 0) with more medics and
victims. A case that passes the limit or the state cap is reported as such, with how far it got.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

CASES = {  # name: a shipped map, or (height, width, rooms, medics, victims)
    "two_rooms": "two_rooms",
    "three_rooms": "three_rooms",
    "gen 12x20, 4 rooms, 2 medics, 4 victims": (12, 20, 4, 2, 4),
    "gen 16x24, 6 rooms, 2 medics, 6 victims": (16, 24, 6, 2, 6),
    "gen 10x15, 2 rooms, 3 medics, 2 victims": (10, 15, 2, 3, 2),
    "gen 10x15, 3 rooms, 3 medics, 3 victims": (10, 15, 3, 3, 3),
    "four_rooms": "four_rooms",
    "office": "office",
}
MAX_STATES = 60_000_000


def one(name: str) -> dict:
    from jaxusar import envs, planning
    from jaxusar.envs import mapgen

    spec = CASES[name]
    env = envs.make(spec if isinstance(spec, str) else mapgen.generated_layout(*spec)[0])
    out = {"medics": env.n_agents, "victims": env.n_victims, "open_cells": int((~env.layout.blocked).sum()),
           "joint_states_bound": float(planning.joint_states_bound(env))}
    t = time.perf_counter()
    out["lower_bound"] = planning.team_lower_bound(env)
    out["lower_bound_seconds"] = round(time.perf_counter() - t, 3)
    stats = {}
    t = time.perf_counter()
    try:
        out["optimum"] = planning._search(env, env.initial_state(), planning._all_triaged, MAX_STATES,
                                          stats=stats)[0]
    except MemoryError as err:
        out["optimum"] = f"stopped: {err}"
    out["search_seconds"] = round(time.perf_counter() - t, 2)
    out["states_visited"] = stats.get("visited")
    out["depth_reached"] = stats.get("depth")
    out["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--one", help=argparse.SUPPRESS)
    p.add_argument("--limit", type=float, default=300, help="seconds per case (default 300)")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "planner_limits.json")
    args = p.parse_args()
    if args.one:
        print(json.dumps(one(args.one)))
        return
    rows = {}
    for name in CASES:
        t = time.perf_counter()
        try:
            run = subprocess.run([sys.executable, __file__, "--one", name], capture_output=True, text=True,
                                 timeout=args.limit)
            if run.returncode == 0:
                row = json.loads(run.stdout.strip().splitlines()[-1])
            else:  # a negative code is the signal: -9 is the kernel's out-of-memory kill
                last = run.stderr.strip().splitlines()[-1:] or [f"killed by signal {-run.returncode}"
                                                                 if run.returncode < 0 else f"exit {run.returncode}"]
                row = {"optimum": f"stopped: {last[0]}"}
        except subprocess.TimeoutExpired:
            row = {"optimum": f"stopped: past the {args.limit:g} s limit"}
        row["wall_seconds"] = round(time.perf_counter() - t, 1)
        rows[name] = row
        print(f"{name:42s} {json.dumps(row)}", flush=True)
    from jaxusar.experiments.train import environment_info

    args.out.write_text(json.dumps({"cases": rows, "max_states": MAX_STATES, "limit_seconds": args.limit,
                                    "environment": environment_info()}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
