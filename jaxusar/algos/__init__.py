"""Learners, one file each, written against jaxusar.core (each file holds only its own math).

The algorithms ``jaxusar train`` runs are the modules here that name themselves with a module-level
``ALGORITHM = "<command-line name>"`` (``registry()`` finds them). Such a module either defines
``make_learner(env, dqn_cfg)`` (a flat learner such as IQL: the shared trainer runs it on the team env;
optional ``DEFAULTS``, a config dict over ``jaxusar.config``'s defaults, and ``DESCRIPTION``, one line
for ``jaxusar train --help``, else the docstring's first line), or names an experiment of its own
with ``EXPERIMENT = "jaxusar.experiments.<file>"`` (the paper's method and option-critic, which train in
stages or once per number of options). The other modules (options, subpolicies) are parts of an
algorithm and are not trained alone.
"""

from __future__ import annotations

import functools
import importlib
import pkgutil
import traceback
from types import ModuleType

from jaxusar.config import ConfigError


class RegistryError(ConfigError):
    """A learner file that cannot be listed, or an algorithm name that names none."""


@functools.cache
def registry() -> dict[str, ModuleType]:
    """{command-line name: module} of every trainable algorithm in this package, sorted by name.

    Every module here is imported once; one that fails to import, names an algorithm twice, or has
    neither ``make_learner`` nor ``EXPERIMENT`` is a RegistryError naming its file."""
    found: dict[str, ModuleType] = {}
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        try:
            module = importlib.import_module(f"{__name__}.{info.name}")
        except Exception as err:  # a fork's file with a bug: name the file and the line, not a traceback
            where = traceback.extract_tb(err.__traceback__)[-1]
            raise RegistryError(f"jaxusar/algos/{info.name}.py cannot be imported: {type(err).__name__}: {err} "
                                f"({where.filename}:{where.lineno})") from None
        name = getattr(module, "ALGORITHM", None)
        if name is None:
            continue
        if not isinstance(name, str) or not name.isidentifier():
            raise RegistryError(f"jaxusar/algos/{info.name}.py: ALGORITHM = {name!r} is not a valid name")
        if name in found:
            raise RegistryError(f"jaxusar/algos/{info.name}.py and {found[name].__name__}: both are ALGORITHM {name!r}")
        if not (hasattr(module, "make_learner") or hasattr(module, "EXPERIMENT")):
            raise RegistryError(f"jaxusar/algos/{info.name}.py (ALGORITHM {name!r}) defines neither "
                                "make_learner(env, dqn_cfg) nor EXPERIMENT")
        found[name] = module
    return dict(sorted(found.items()))


def algorithm(name: str) -> ModuleType:
    """The module of algorithm ``name``; an unknown name is a RegistryError listing the known ones."""
    known = registry()
    if name not in known:
        raise RegistryError(f"unknown algorithm {name!r}; available: {', '.join(known)}")
    return known[name]


def defaults(name: str) -> dict:
    """The config defaults of algorithm ``name``: ``{"algo": name}`` and its module's ``DEFAULTS``."""
    return {"algo": name, **getattr(algorithm(name), "DEFAULTS", {})}


def describe(module: ModuleType) -> str:
    """One line on an algorithm: its ``DESCRIPTION``, else its docstring's first line."""
    return getattr(module, "DESCRIPTION", None) or ((module.__doc__ or "").strip().splitlines() or [""])[0]
