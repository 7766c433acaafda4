"""How `jaxusar reproduce --quick` grows with the number of trials: wall seconds and peak memory.

Runs ``jaxusar reproduce --quick --trials N`` for each N (default 8, 16, 32, 64), one after another, each
in its own process (peak memory is a per-process number) with the compilation cache off (every run pays
its compilation, as a first run does), then writes ``benchmarks/results/scaling.json`` and
``scaling.png``: seconds and peak resident memory against trials, with the linear reference through the
smallest run (cost proportional to trials). Example::

    python benchmarks/scaling.py                      # 8, 16, 32, 64 trials
    python benchmarks/scaling.py --trials 8 16        # a quick look
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from jaxusar.experiments.train import cpu_name  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def measure(trials: int, folder: Path) -> dict:
    out = folder / f"trials{trials}"
    cmd = [sys.executable, "-m", "jaxusar", "reproduce", "--quick", "--trials", str(trials), "--out", str(out),
           "--quiet", "--no-compile-cache"]
    subprocess.run(cmd, check=True)
    r = json.loads((out / "results.json").read_text())
    return {"trials": trials, "wall_seconds": r["wall_seconds"], "peak_rss_mb": r["usage"]["peak_rss_mb"],
            "programs": r["usage"]["programs"], "seconds_by_algorithm": r["seconds_by_algorithm"]}


def plot(rows: list[dict], path: Path) -> None:
    n = [r["trials"] for r in rows]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, label in zip(axes, ("wall_seconds", "peak_rss_mb"), ("wall seconds", "peak resident memory (MiB)")):
        y = [r[key] for r in rows]
        ax.plot(n, y, "o-", label="measured")
        ax.plot(n, [y[0] * k / n[0] for k in n], "--", color="grey", label=f"linear: {n[0]} trials' cost x trials / {n[0]}")
        ax.set_xlabel("trials per algorithm")
        ax.set_ylabel(label)
        ax.set_xticks(n)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"jaxusar reproduce --quick, compile cache off ({cpu_name()})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, nargs="+", default=[8, 16, 32, 64])
    args = parser.parse_args()
    if any(t < 1 for t in args.trials):
        parser.error(f"--trials must all be >= 1, got {args.trials}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="jaxusar-scaling-") as tmp:
        for t in sorted(args.trials):
            rows.append(measure(t, Path(tmp)))
            print(json.dumps(rows[-1]), flush=True)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "scaling.json").write_text(json.dumps({"machine": cpu_name(), "rows": rows}, indent=2))
    plot(rows, RESULTS / "scaling.png")
    print(f"wrote {RESULTS / 'scaling.json'} and {RESULTS / 'scaling.png'}")


if __name__ == "__main__":
    main()
