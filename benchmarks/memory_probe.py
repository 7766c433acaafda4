"""Two memory costs outside the trainer states, measured in this process (Linux: /proc and ru_maxrss).

* ``save``: how much a checkpoint save of the paper's sub-policy state (``--trials`` trials, freshly
  initialised) raises the process's peak resident memory, and how long it takes.
* ``compile``: resident memory after compiling that trainer's chunk, then after
  ``usage.release_memory()`` (what glibc kept of the memory the compile freed).

Run it at a commit to measure that commit's checkpoint format (``git checkout 18acf94`` for the format-2
save). Intel Xeon numbers in benchmarks/README.md ("What was left").

    python benchmarks/memory_probe.py save --trials 32
    python benchmarks/memory_probe.py compile --trials 8
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import jax

from jaxusar.core import checkpoint
from jaxusar.experiments import reproduce, train


def rss_mib() -> float:
    return int(next(line for line in open("/proc/self/status") if line.startswith("VmRSS")).split()[1]) / 1024


def peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("save", "compile"))
    ap.add_argument("--trials", type=int, default=8)
    args = ap.parse_args()
    if args.trials < 1:
        ap.error(f"--trials must be >= 1, got {args.trials}")
    stage = train.experiment(reproduce.configs()["hierarchical"], train.trial_keys(0, args.trials)).chains[0][0]
    state = jax.block_until_ready(stage.trainer.init(stage.keys, stage.env_params))
    print(f"{stage.name}, {len(stage.keys)} lanes: resident {rss_mib():.0f} MiB, peak {peak_mib():.0f} MiB")
    if args.what == "save":
        with tempfile.TemporaryDirectory() as folder:
            start = time.perf_counter()
            checkpoint.save(Path(folder) / "probe.ckpt", state, {})
            print(f"after a checkpoint save ({time.perf_counter() - start:.1f} s): peak {peak_mib():.0f} MiB")
    else:
        from jaxusar.experiments.usage import release_memory

        stage.trainer.compile(state)
        print(f"after compiling the chunk: resident {rss_mib():.0f} MiB")
        release_memory()
        print(f"after release_memory(): resident {rss_mib():.0f} MiB")


if __name__ == "__main__":
    main()
