"""What a run uses besides seconds, and JAX's persistent compilation cache.

* ``Usage``: counts the XLA programs a run asked for (each ``jit`` of a new shape or function), how many
  of them were loaded from the persistent compilation cache instead of compiled, and reads the
  process's peak resident memory. ``jaxusar train`` and ``jaxusar reproduce`` record it in
  metrics.json / results.json (``usage``).
* ``release_memory``: hands the memory the process has freed back to the system (glibc keeps it
  otherwise: an XLA compile frees some 300 MB that would stay resident), so the next stage's or
  chunk's peak does not stack on it. The runner calls it after every compile and chunk.
* ``enable_compile_cache``: the persistent cache, on by default for those commands, in the user's
  cache folder, so a second run with the same arguments loads its programs instead of compiling them.
  Off with ``--no-compile-cache`` or ``JAXUSAR_COMPILE_CACHE=0``; ``JAX_COMPILATION_CACHE_DIR`` picks
  the folder. A folder that cannot be written is a warning and the run goes on without the cache; a
  corrupted entry is JAX's own warning, and that program is compiled again.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import resource
import sys
import threading
import warnings
from pathlib import Path

import jax
from jax import monitoring

_BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"  # every program, compiled or loaded
_CACHE_HIT = "/jax/compilation_cache/cache_hits"
_lock = threading.Lock()
_counts = {"programs": 0, "loaded": 0}


def _on_duration(event: str, duration_secs: float, **kwargs) -> None:
    if event == _BACKEND_COMPILE:
        with _lock:
            _counts["programs"] += 1


def _on_event(event: str, **kwargs) -> None:
    if event == _CACHE_HIT:
        with _lock:
            _counts["loaded"] += 1


monitoring.register_event_duration_secs_listener(_on_duration)
monitoring.register_event_listener(_on_event)


def peak_rss_mb() -> float:
    """This process's peak resident memory so far, in MiB (threads included; Linux reports KiB)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (2**20 if sys.platform == "darwin" else 2**10), 1)


def _libc():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc if hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


_LIBC = _libc() if sys.platform.startswith("linux") else None


def release_memory() -> None:
    """Return freed heap memory to the system (glibc's ``malloc_trim``; a no-op where there is none)."""
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


class Usage:
    """Programs and memory from construction on: ``Usage().report()`` after the work."""

    def __init__(self):
        with _lock:
            self.start = dict(_counts)

    def report(self) -> dict:
        with _lock:
            programs = _counts["programs"] - self.start["programs"]
            loaded = _counts["loaded"] - self.start["loaded"]
        return {"programs": programs, "programs_compiled": programs - loaded, "programs_loaded_from_cache": loaded,
                "peak_rss_mb": peak_rss_mb(), "compile_cache": jax.config.jax_compilation_cache_dir}


def default_cache_folder() -> Path:
    """``$JAX_COMPILATION_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxusar/xla`` (``~/.cache/jaxusar/xla``)."""
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return Path(os.environ["JAX_COMPILATION_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "jaxusar" / "xla"


def enable_compile_cache(enabled: bool = True, folder: str | Path | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``folder`` (default: ``default_cache_folder()``);
    returns the folder, or None when it is off (``enabled`` False, ``JAXUSAR_COMPILE_CACHE=0``, or a
    folder that cannot be written: a warning)."""
    if not enabled or os.environ.get("JAXUSAR_COMPILE_CACHE", "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    folder = Path(folder) if folder is not None else default_cache_folder()
    probe = folder / f".jaxusar-write-test-{os.getpid()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        warnings.warn(f"the compilation cache folder {str(folder)!r} cannot be written ({err.strerror or err}); "
                      "running without the cache (set JAX_COMPILATION_CACHE_DIR to another folder, or "
                      "JAXUSAR_COMPILE_CACHE=0 to silence this)", stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder
