"""How many lane-steps the paper's method's sub-policy stage pays, by chunk length and batch buckets.

A sub-policy lane stops at its first test that is exact from every initiation state, but a vmap cannot
stop one lane: it steps on to its chunk's end, and between chunks the still-running lanes are padded to a
bucket (``trainer.batch_bucket``). From a finished run's curves (``DIR/curves.csv`` and ``metrics.json``
of ``jaxusar train hierarchical`` or of ``reproduce``'s ``hierarchical/``), this replays each lane's env
steps up to that test and counts what each chunk length and bucket rule would step in all. No training
runs; the lanes' own steps do not depend on either, the in-chunk random numbers aside.

    python benchmarks/lane_steps.py results/office/hierarchical --chunks 4000 2000 1000 500
"""

from __future__ import annotations

import argparse
import collections
import csv
import json
from pathlib import Path

from jaxusar.core.trainer import batch_bucket


def needed_steps(run: Path) -> list[int]:
    """Each sub-policy lane's env steps up to its first exact test (its whole run where it had none)."""
    per_task = json.loads((run / "metrics.json").read_text())["subpolicy_episodes_to_optimal"]["per_task"]
    steps = collections.defaultdict(list)
    with open(run / "curves.csv") as f:
        for row in csv.DictReader(f):
            if row["stage"] == "subpolicy" and row["kind"] == "train" and row["steps"]:
                steps[row["task"], int(row["trial"])].append(int(float(row["steps"])))
    return [sum(s[:per_task[task][trial] or len(s)]) for (task, trial), s in steps.items()]


def lane_steps(needed: list[int], chunk: int, bucket) -> tuple[int, int]:
    """(chunks, lane-steps) with ``chunk`` env steps per chunk and ``bucket(live) -> batch``."""
    total, k = 0, 0
    while live := sum(n > k * chunk for n in needed):
        total += min(bucket(live), len(needed)) * chunk
        k += 1
    return k, total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a hierarchical results folder (curves.csv, metrics.json)")
    ap.add_argument("--chunks", type=int, nargs="+", default=[4000, 2000, 1000, 500])
    args = ap.parse_args()
    needed = needed_steps(args.run)
    power_of_two = lambda n: 1 << (max(n, 1) - 1).bit_length()
    print(f"{args.run}: {len(needed)} lanes, {sum(needed) / 1e6:.2f}M env steps up to their first exact test")
    for chunk in args.chunks:
        for name, bucket in (("powers of two", power_of_two), ("batch_bucket", batch_bucket)):
            k, total = lane_steps(needed, chunk, bucket)
            print(f"  chunk {chunk:>5}, {name:<13}: {k:>3} chunks, {total / 1e6:.2f}M lane-steps")


if __name__ == "__main__":
    main()
