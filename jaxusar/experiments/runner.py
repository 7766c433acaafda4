"""Run an experiment's trainers: compile, train in chunks with atomic checkpoints, resume, shard, time.

Vocabulary::

    Stage    one Trainer over a batch of lanes (trials, or the hierarchical method's task x trial lanes):
             compiled once, run chunk by chunk, checkpointed as ``<checkpoints>/<name>.ckpt``
    chain    stages run one after another; a later stage's env params may be computed from the
             previous stage's results (the coordinator runs over the sub-policies' best params)
    Runner   runs independent chains side by side in threads (XLA releases the GIL; on a CPU one
             vmapped call keeps about one core busy), longest first as the caller orders them

Resuming: a stage whose checkpoint exists continues from it. The checkpoint's configuration
fingerprint and lane count are checked first (a changed setting or --trials is refused in words), its
array shapes last (a map file or the code changed since), each refusal a CheckpointError that says to
pass --force; a finished stage's final state is kept, so a re-run after a kill at any point redoes at
most the chunks since the last checkpoint. All randomness of chunk ``c`` comes from
``fold_in(trial_key, c)``, so resumed results equal uninterrupted ones.

Ctrl-C (SIGINT): ``Runner.interrupted()`` gives an ``Interrupted`` whose message says where the last
checkpoints are and that the same command resumes from them. Chains running in threads are told to stop
after their chunk and are not waited for (a chunk of a big run takes minutes); the caller then ends the
process (``Interrupted.abandoned_threads``), which loses nothing a SIGKILL would not.

Several processes (``jax.distributed``): each runs its own slice of the trials on its local devices,
with its own checkpoints; ``gather`` then concatenates every stage's results over processes.
"""

from __future__ import annotations

import dataclasses
import threading
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


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during a run; the message says where its checkpoints are and how to resume (a
    KeyboardInterrupt still, so nothing on its way up mistakes it for an error to handle).

    ``abandoned_threads``: chains were still running in threads when it came; the process should end
    without waiting for them (``os._exit``), as their checkpoints are atomic."""

    def __init__(self, message: str, abandoned_threads: bool = False):
        super().__init__(message)
        self.abandoned_threads = abandoned_threads


class _Stopped(Exception):
    """Raised in a chain's thread after its chunk once the run was interrupted."""


class Runner:
    """Runs chains of stages with checkpoints in ``folder`` (created on demand).

    Args:
      fingerprint: identifies the configuration; a checkpoint with another one is refused.
      checkpoint_every: seconds between checkpoints (one is always written at a stage's end); 0 = every chunk.
      devices: the trials axis is sharded over these (default: every local device).
      progress: called as progress(stage_name, info) after each chunk (see Trainer.train), and once when a
        stage resumes from a checkpoint, with info ``{"resumed_from": path, "chunk", "finished",
        "run_seconds"}``; or None.
    """

    def __init__(self, folder: str | Path, fingerprint: str, checkpoint_every: float = 60.0, devices=None,
                 progress: Callable[[str, dict], None] | None = None):
        self.folder, self.fingerprint = Path(folder), fingerprint
        self.checkpoint_every, self.devices, self.progress = checkpoint_every, devices, progress
        self.stopping = threading.Event()  # set on Ctrl-C: chains in threads stop after their chunk
        self.abandoned_threads = False

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
        pool, futures = ThreadPoolExecutor(min(workers, len(chains))), []
        try:
            futures = [pool.submit(self.run_chain, chain) for chain in chains]
            return {k: v for f in futures for k, v in f.result().items()}
        except KeyboardInterrupt:
            # waiting for the threads would wait for their chunks: tell them to stop, and leave them
            self.stopping.set()
            self.abandoned_threads = any(not f.done() for f in futures)
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        finally:
            if not self.stopping.is_set():
                pool.shutdown(wait=True)

    def interrupted(self) -> Interrupted:
        """The ``Interrupted`` of a Ctrl-C now: where this run's checkpoints are, and that the same command
        resumes from them (or that there is nothing to resume yet)."""
        self.stopping.set()
        kept = []
        for path in sorted(self.folder.glob("*.ckpt")) if self.folder.is_dir() else []:
            try:
                meta = checkpoint.read_meta(path)
            except CheckpointError:
                continue
            if meta.get("fingerprint") == self.fingerprint:
                kept.append((path, meta))
        if not kept:
            text = "interrupted before the first checkpoint: nothing to resume, the same command starts over"
        else:
            where = ", ".join(f"{m.get('stage')} " + ("finished" if m.get("finished") else f"after chunk {m.get('chunk')}")
                              for _, m in kept)
            place = str(kept[0][0]) if len(kept) == 1 else f"in {self.folder}"
            text = (f"interrupted; the last checkpoint{'s are' if len(kept) > 1 else ' is'} {place} ({where}); "
                    "the same command resumes from there")
        return Interrupted(text, self.abandoned_threads)

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
            # the configuration before the shapes: a changed budget changes both, and only the first says why
            self.check_fits(path, checkpoint.read_meta(path), stage)
            try:
                state, meta = checkpoint.load(path, jax.eval_shape(trainer.init, stage.keys, env_params))
            except CheckpointError as err:
                raise CheckpointError(f"{err}: it does not fit this run's state (the map file or jaxusar changed "
                                      "since it was written); pass --force to start over") from None
            resumed = int(meta["chunk"])
            if self.progress is not None:
                self.progress(stage.name, {"resumed_from": str(path), "chunk": resumed,
                                           "finished": bool(meta["finished"]), "run_seconds": meta["run_seconds"]})
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
            if self.stopping.is_set():  # Ctrl-C in the main thread; this chain runs in a thread
                raise _Stopped()
            # JAX dispatches a chunk asynchronously: ``done`` reads its results, so it has run before the clock
            # is read (read first, the clock said a checkpoint was due when the previous chunk had taken long)
            finished = trainer.done(s)
            release_memory()  # what the chunk freed (a smaller batch's first chunk also compiles its program)
            if not finished and time.perf_counter() - last_save >= self.checkpoint_every:
                save(s)

        progress = None if self.progress is None else (
            lambda info: None if self.stopping.is_set() else self.progress(stage.name, info))
        state = trainer.train(stage.keys, progress=progress, state=state, on_chunk=on_chunk)
        save(state, finished=True)
        outcome = Outcome(trainer.results(state), compile_seconds, meta["run_seconds"], int(state.chunk), resumed,
                          light(state))
        trainer.release_programs()
        return outcome

    def check_fits(self, path: Path, meta: dict, stage: Stage) -> None:
        """Refuse, in words, a checkpoint of another configuration, stage or number of lanes (trials)."""
        if meta.get("fingerprint") != self.fingerprint or meta.get("stage") != stage.name:
            raise CheckpointError(
                f"{path} was written by another configuration ({meta.get('fingerprint')}, this run is "
                f"{self.fingerprint}: a setting or --trials changed); pass --force to start over, or --out DIR "
                "to run this one in another folder")
        if meta.get("lanes", len(stage.keys)) != len(stage.keys):
            raise CheckpointError(f"{path} was written by a run of {meta['lanes']} lanes, this one has "
                                  f"{len(stage.keys)} (another --trials?); pass --force to start over, or --out DIR "
                                  "to run this one in another folder")


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


__all__ = ["Stage", "Outcome", "Runner", "Interrupted", "gather", "CheckpointError"]
