"""The exact ceiling of the paper's method's option set on a map: the fewest team steps any coordinator can
reach, over exact sub-policies.

A uniform-cost search over the coordinator's decisions (a decision's cost: the primitive steps its options
ran), each agent choosing among its valid options (``MacroEnv.valid_options``) at every decision, the
sub-policies exact (``subpolicies.exact_subpolicies``), the map's default coordinator rules (termination,
dodge, timeouts) and ``--set`` overrides. No learning: where it is above the map's optimum, no coordinator
over these options reaches the optimum, however it is trained. It prints the fewest steps and one plan.

    python benchmarks/option_ceiling.py --map two_rooms_rubble
    python benchmarks/option_ceiling.py --map two_rooms_rubble --set hierarchical.coordinator.termination=all
"""

from __future__ import annotations

import argparse
import itertools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxusar import algos, config
from jaxusar.algos import coordinator as coord
from jaxusar.algos import subpolicies as sp
from jaxusar.experiments import hierarchical


def ceiling(map_name: str, sets: tuple[str, ...] = (), limit: int | None = None, batch: int = 4096) -> dict:
    """{"steps": fewest team steps (None: none within ``limit``, default the horizon), "plan": the decisions
    of one such plan, "reference": the map's, "macro_states": how many were expanded}."""
    cfg = config.load(None, [f"env.map={map_name}", *sets, "hierarchical.coordinator.kind=factored"],
                      defaults=algos.defaults("hierarchical"))
    b = hierarchical.build(cfg)
    macro = b["macro"]
    p = coord.CoordinatorParams(subpolicy=sp.exact_subpolicies(b["subtask_env"], b["task_params"]))
    limit = macro.horizon if limit is None else limit
    step = jax.jit(jax.vmap(lambda s, a: macro.step(None, s, a, p)[1:5:3]))  # (state, info)
    choices = jax.jit(jax.vmap(lambda s: (macro.valid_options(macro.observe(s)),
                                          macro.available(*macro.decode(macro.observe(s))).any(-1))))
    _, s0 = macro.reset(jax.random.PRNGKey(0))
    treedef = jax.tree.structure(s0)
    as_leaves = lambda s: tuple(np.asarray(x) for x in jax.tree.leaves(s))
    stack = lambda states: jax.tree.unflatten(treedef, [jnp.asarray(np.stack(x)) for x in zip(*states)])
    buckets, parent, expanded = {0: [(as_leaves(s0), None)]}, {}, 0
    for g in range(limit + 1):
        fresh = []
        for leaves, via in buckets.pop(g, []):
            key = b"".join(x.tobytes() for x in leaves)
            if key not in parent:
                parent[key] = via
                fresh.append((leaves, key))
        if not fresh:
            continue
        states = stack([leaves for leaves, _ in fresh])
        done = np.asarray(states.env.triaged).all(-1)
        if done.any():
            plan, key = [], fresh[int(np.argmax(done))][1]
            while parent[key] is not None:
                key, options, k = parent[key]
                plan.append(([macro.options.names[o] for o in options], k))
            return {"steps": g, "plan": plan[::-1], "reference": b["reference"], "macro_states": expanded}
        valid, active = map(np.asarray, choices(states))
        todo = [(i, a) for i in range(len(fresh))
                for a in itertools.product(*[np.flatnonzero(valid[i, j]) if active[i, j] else [0]
                                             for j in range(macro.n_agents)])]
        expanded += len(fresh)
        for lo in range(0, len(todo), batch):
            idx = np.array([i for i, _ in todo[lo:lo + batch]])
            acts = np.array([a for _, a in todo[lo:lo + batch]], np.int32)
            nxt, info = step(jax.tree.map(lambda x: x[idx], states), jnp.asarray(acts))
            nxt, k, ok = as_leaves(nxt), np.asarray(info["steps"]), np.asarray(info["valid"])
            for j in np.flatnonzero(ok):
                buckets.setdefault(g + int(k[j]), []).append(
                    (tuple(x[j] for x in nxt), (fresh[idx[j]][1], acts[j].tolist(), int(k[j]))))
    return {"steps": None, "plan": [], "reference": b["reference"], "macro_states": expanded}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--map", default="two_rooms_rubble", help="shipped map name or layout path")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config overrides")
    p.add_argument("--limit", type=int, default=None, help="give up above this many team steps (default: horizon)")
    args = p.parse_args()
    t = time.perf_counter()
    out = ceiling(args.map, tuple(args.set), args.limit)
    ref = out["reference"]
    print(f"{args.map}: the option set's ceiling is {out['steps']} team steps (reference: {ref['reference']} "
          f"{ref['steps']}); {out['macro_states']:,} decision states expanded in {time.perf_counter() - t:.0f} s")
    for options, k in out["plan"]:
        print(f"  {k:3d} steps  {' | '.join(options)}")


if __name__ == "__main__":
    main()
