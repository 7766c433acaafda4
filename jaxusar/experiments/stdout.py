"""Printing from threads that should read as if the work ran one piece after another.

``per_thread()`` installs a ``sys.stdout`` that sends a thread's writes to the buffer ``captured()`` gave
that thread, and every other write where it went before; the caller prints each buffer when its piece is
done, in its own order (``benchmark.score_all``: each pair's lines together, in pair order).
"""

from __future__ import annotations

import contextlib
import io
import sys
import threading


class _PerThread(io.TextIOBase):
    def __init__(self, real):
        self.real, self.local = real, threading.local()

    def _target(self):
        buffer = getattr(self.local, "buffer", None)
        return self.real if buffer is None else buffer

    def write(self, text: str) -> int:
        return self._target().write(text)

    def flush(self) -> None:
        self._target().flush()

    def isatty(self) -> bool:
        return self.real.isatty()

    @property
    def encoding(self):
        return self.real.encoding


@contextlib.contextmanager
def per_thread():
    """Inside: ``sys.stdout`` writes each thread's text to its ``captured`` buffer, if it has one."""
    real = sys.stdout
    sys.stdout = _PerThread(real)
    try:
        yield
    finally:
        sys.stdout = real


@contextlib.contextmanager
def captured():
    """This thread's printed text, into the StringIO it yields (inside ``per_thread``; elsewhere it
    redirects ``sys.stdout`` as ``contextlib.redirect_stdout`` does)."""
    buffer, out = io.StringIO(), sys.stdout
    if not isinstance(out, _PerThread):
        with contextlib.redirect_stdout(buffer):
            yield buffer
        return
    out.local.buffer = buffer
    try:
        yield buffer
    finally:
        out.local.buffer = None
