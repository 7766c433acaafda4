"""Run an experiment's trainers: compile, train in chunks with atomic checkpoints, resume, shard, time.

Vocabulary::

    Stage    one Trainer over a batch of lanes (trials, or the hierarchical method's task x trial lanes):
             compiled once, run chunk by chunk, checkpointed as ``<checkpoints>/<name>.ckpt``
    chain    stages run one after another; a later stage's env params may be computed from the
             previous stage's results (the coordinator runs over the sub-policies' best params)
    Runner   runs independent chains side by side in threads (XLA releases the GIL; on a CPU one
             vmapped call keeps about one core busy), longest first as the caller orders them

Resuming: a stage whose checkpoint exists continues from it (same config fingerprint, same shapes,
else a CheckpointError that says to pass --force); a finished stage's final state is kept, so a
re-run after a kill at any point redoes at most the chunks since the last checkpoint. All randomness
of chunk ``c`` comes from ``fold_in(trial_key, c)``, so resumed results equal uninterrupted ones.

Several processes (``jax.distributed``): each runs its own slice of the trials on its local devices,
with its own checkpoints; ``gather`` then concatenates every stage's results over processes.
"""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable

import jax

from jaxusar.core import Trainer, checkpoint
from jaxusar.core.checkpoint import CheckpointError
from jaxusar.experiments.usage import release_memory


@dataclasses.dataclass
class Stage:
    name: str              # unique in a run ("iql", "doc/K4", "hierarchical/coordinator")
    trainer: Trainer
    keys: jax.Array        # one PRNG key per lane
    env_params: Any = None  # per-lane env params, or a function of the previous stage's Outcome


@dataclasses.dataclass
class Outcome:
    results: dict              # Trainer.results (over every process's trials after ``gather``)
    compile_seconds: float     # init + chunk compilation in this session (0 if it was finished before)
    run_seconds: float         # chunks, summed over every session that worked on this stage
    chunks: int
    resumed_from_chunk: int | None  # the checkpoint's chunk when this session resumed it, else None
    state: Any = dataclasses.field(default=None, repr=False)  # final TrainState of this process's lanes, but
    # for what results read (``light``): a finished stage's replay is not held while the next stages run


class Runner:
    """Runs chains of stages with checkpoints in ``folder`` (created on demand).

    Args:
      fingerprint: identifies the configuration; a checkpoint with another one is refused.
      checkpoint_every: seconds between checkpoints (one is always written at a stage's end); 0 = every chunk.
      devices: the trials axis is sharded over these (default: every local device).
      progress: called as progress(stage_name, info) after each chunk (see Trainer.train), or None.
    """

    def __init__(self, folder: str | Path, fingerprint: str, checkpoint_every: float = 60.0, devices=None,
                 progress: Callable[[str, dict], None] | None = None):
        self.folder, self.fingerprint = Path(folder), fingerprint
        self.checkpoint_every, self.devices, self.progress = checkpoint_every, devices, progress

    def path(self, stage: Stage) -> Path:
        """``<folder>/<stage>.ckpt``; with several processes each has its own (``<stage>.p<i>.ckpt``)."""
        process = f".p{jax.process_index()}" if jax.process_count() > 1 else ""
        return self.folder / f"{stage.name.replace('/', '.')}{process}.ckpt"

    def run(self, chains: list[list[Stage]], workers: int = 1) -> dict[str, Outcome]:
        """Every chain, up to ``workers`` at once, in the order given; returns {stage name: Outcome}."""
        names = [s.name for chain in chains for s in chain]
        if len(set(names)) != len(names):
            raise ValueError(f"stage names must be unique: {names}")
        self.folder.mkdir(parents=True, exist_ok=True)
        if workers <= 1 or len(chains) <= 1:
            return {k: v for chain in chains for k, v in self.run_chain(chain).items()}
        with ThreadPoolExecutor(min(workers, len(chains))) as pool:
            futures = [pool.submit(self.run_chain, chain) for chain in chains]
            return {k: v for f in futures for k, v in f.result().items()}

    def run_chain(self, chain: list[Stage]) -> dict[str, Outcome]:
        outcomes, previous = {}, None
        for stage in chain:
            previous = outcomes[stage.name] = self.run_stage(stage, previous)
        return outcomes

    def run_stage(self, stage: Stage, previous: Outcome | None = None) -> Outcome:
        trainer, path = stage.trainer, self.path(stage)
        env_params = stage.env_params(previous) if callable(stage.env_params) else stage.env_params
        meta = {"fingerprint": self.fingerprint, "stage": stage.name, "lanes": int(len(stage.keys)),
                "chunk": 0, "run_seconds": 0.0, "finished": False}
        resumed = None
        start = time.perf_counter()
        if path.exists():
            state, meta = checkpoint.load(path, jax.eval_shape(trainer.init, stage.keys, env_params))
            if meta.get("fingerprint") != self.fingerprint or meta.get("stage") != stage.name:
                raise CheckpointError(
                    f"{path} was written by another configuration ({meta.get('fingerprint')}, this run is "
                    f"{self.fingerprint}); pass --force to start over")
            resumed = int(meta["chunk"])
            if meta["finished"]:
                return Outcome(trainer.results(state), 0.0, meta["run_seconds"], resumed, resumed, light(state))
        else:
            state = trainer.init(stage.keys, env_params)
        state = trainer.place(state, self.devices)
        trainer.compile(state)
        release_memory()
        compile_seconds = time.perf_counter() - start
        earlier_run, run_start = meta["run_seconds"], time.perf_counter()
        last_save = run_start

        def save(s, finished=False):
            nonlocal last_save
            last_save = time.perf_counter()
            meta.update(chunk=int(s.chunk), finished=finished, run_seconds=earlier_run + last_save - run_start)
            checkpoint.save(path, s, meta)

        def on_chunk(s):
            # JAX dispatches a chunk asynchronously: ``done`` reads its results, so it has run before the clock
            # is read (read first, the clock said a checkpoint was due when the previous chunk had taken long)
            finished = trainer.done(s)
            release_memory()  # what the chunk freed (a smaller batch's first chunk also compiles its program)
            if not finished and time.perf_counter() - last_save >= self.checkpoint_every:
                save(s)

        progress = None if self.progress is None else (lambda info: self.progress(stage.name, info))
        state = trainer.train(stage.keys, progress=progress, state=state, on_chunk=on_chunk)
        save(state, finished=True)
        return Outcome(trainer.results(state), compile_seconds, meta["run_seconds"], int(state.chunk), resumed,
                       light(state))


def light(state):
    """``state`` with only what ``Trainer.results`` reads (no learner, replay, snapshots or env state)."""
    return state.replace(trials=state.trials.replace(learner=None, snaps=None, actor=None, env_state=None, obs=None,
                                                     env_params=None))


def gather(outcomes: dict[str, Outcome], stages: dict[str, Stage]) -> dict[str, Outcome]:
    """With several processes: every stage's results over all processes' lanes, in process order
    (a no-op in one process). Only what ``Trainer.results`` reads is sent (``Outcome.state`` is ``light``)."""
    if jax.process_count() == 1:
        return outcomes
    from jax.experimental import multihost_utils

    out = {}
    for name, o in outcomes.items():
        full = multihost_utils.process_allgather(o.state, tiled=True)
        out[name] = dataclasses.replace(o, results=stages[name].trainer.results(full), state=None)
    return out


__all__ = ["Stage", "Outcome", "Runner", "gather", "CheckpointError"]
