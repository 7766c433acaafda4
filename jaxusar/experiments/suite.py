"""The benchmark's task suite: versioned tasks, each a map with its observation, horizon and test draws fixed.

A task id names a map and a version (``two_rooms-v1``): the version changes whenever anything that moves a
task's numbers changes (its map, observation, horizon, test draws, the generator's output or the env
contract), so that a score quoted with an id keeps its meaning. Generated maps carry the sha256 of the
layout text their generator arguments must give; ``materialize`` refuses a generator that now draws
another map, rather than benchmark a different task under the same id.

Adding a task: one ``Task`` in ``TASKS`` (a new version of a task is a new entry; old ones stay listed).
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

from jaxusar.config import ConfigError


@dataclasses.dataclass(frozen=True)
class Task:
    name: str                  # the map's name in the id
    version: int
    map: str                   # a shipped map's name, or ``generated`` (then ``generator`` holds its arguments)
    observation: str = "full"  # the env's observation mode for every algorithm
    horizon: int = 300         # the episode cap (training and tests)
    test_draws: int = 32       # victims drawn at reset: the fixed draws a trial is scored on (seed ``draw_seed``)
    draw_seed: int = 0
    generator: tuple = ()      # ``mapgen.generated_layout`` arguments, as (key, value) pairs
    sha256: str = ""           # of the generated layout text

    @property
    def id(self) -> str:
        return f"{self.name}-v{self.version}"

    def describe(self) -> str:
        where = "generated " + ", ".join(f"{k}={v}" for k, v in self.generator) if self.map == "generated" \
            else f"map {self.map}"
        return f"{where}; observation {self.observation}; horizon {self.horizon}"


TASKS = {t.id: t for t in (
    Task("two_rooms", 1, "two_rooms"),
    Task("three_rooms", 1, "three_rooms"),
    Task("four_rooms", 1, "four_rooms"),
    Task("office", 1, "office"),
    Task("two_rooms_rubble", 1, "two_rooms_rubble"),
    Task("minimap", 1, "minimap", observation="view"),
    Task("gen_9x13", 1, "generated", generator=(("height", 9), ("width", 13), ("rooms", 3), ("medics", 2),
                                                ("victims", 3), ("seed", 1)),
         sha256="495c4e25ef42ace141b475045a78ba3dec73f15958a1f55b8a08c5d524c7bc6b"),
    Task("gen_12x16", 1, "generated", generator=(("height", 12), ("width", 16), ("rooms", 4), ("medics", 3),
                                                 ("victims", 4), ("seed", 2)),
         sha256="e2dc17b29518d957857a3d9a2b67525ee9f488e024806520b002272fd8f2b85f"),
)}


def resolve(ids: list[str] | None) -> list[Task]:
    """The tasks of ``ids`` (default: every task at its latest version), in suite order; an unknown id or
    version is a ConfigError naming what exists."""
    latest = {}
    for t in TASKS.values():
        latest[t.name] = max(latest.get(t.name, t), t, key=lambda x: x.version)
    if not ids:
        return list(latest.values())
    out = []
    for i in ids:
        if i in TASKS:
            out.append(TASKS[i])
            continue
        name = i.rsplit("-v", 1)[0]
        versions = [t.id for t in TASKS.values() if t.name == name]
        if versions:
            raise ConfigError(f"unknown task version {i!r}; {name} has {', '.join(versions)}")
        raise ConfigError(f"unknown task {i!r}; tasks: {', '.join(TASKS)} (jaxusar benchmark --list)")
    if len(set(out)) != len(out):
        raise ConfigError(f"--tasks names a task twice: {' '.join(ids)}")
    return sorted(out, key=list(TASKS.values()).index)


def materialize(task: Task, folder: Path) -> str:
    """The ``env.map`` of ``task``: a shipped map's name, or a generated map written to ``folder`` (its
    layout and region grid) after checking the layout's sha256."""
    if task.map != "generated":
        return task.map
    from jaxusar.envs.mapgen import generated_layout

    _, text, regions = generated_layout(**dict(task.generator), name=task.name)
    digest = hashlib.sha256(text.encode()).hexdigest()
    if digest != task.sha256:
        raise ConfigError(f"task {task.id}: the generator now draws another map (sha256 {digest[:12]}, the task's "
                          f"{task.sha256[:12]}); a changed map is a new task version")
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{task.name}.txt"
    path.write_text(text)
    (folder / f"{task.name}.regions.txt").write_text(regions)
    return str(path)
