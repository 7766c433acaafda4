"""Test-session settings: one persistent XLA compilation cache for the whole session (and the CLI
subprocesses the tests start), so a program compiled by one test (e.g. a reproduction's trainers)
is loaded, not recompiled, by the next. It changes no numbers: a cached executable is the same one."""

import os
import tempfile

import jax

CACHE = os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", tempfile.mkdtemp(prefix="jaxusar-xla-cache-"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
jax.config.update("jax_compilation_cache_dir", CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)


def pytest_collection_modifyitems(items):
    """The longest file first (its module-scoped reproduction and subprocess runs take about half the
    suite), so that with `-n 2 --dist loadfile` (pyproject.toml) the other worker takes every other file
    meanwhile. Within a file the order is kept."""
    items.sort(key=lambda item: item.nodeid.split("::")[0] != "tests/test_reproduce.py")
