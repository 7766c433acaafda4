"""Atomic run checkpoints: one pytree (a trainer's whole state) and a small metadata dict per file.

A checkpoint is written to ``<path>.tmp``, flushed to disk, then renamed over ``<path>`` (a rename is
atomic on POSIX), so a run killed at any moment leaves either the previous checkpoint or the new one,
never half of one. The file is an uncompressed zip: ``meta.json`` (with the format number) and the
pytree's flat list of leaves as ``leaves/<i>.npy``, written one array at a time in numpy's own chunks,
so saving costs no second copy of the state (a 64-trial sub-policy state is 0.75 GiB; serializing it
into one message first, as format 2 did, doubled the run's memory for the length of the save). ``load``
rebuilds the tree on the structure of a template (e.g. ``jax.eval_shape`` of the trainer's init) and
refuses a file whose leaves do not match the template's shapes and dtypes. Format-2 files (one msgpack
message, the same arrays) are still read.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import jax
import numpy as np
from flax import serialization

FORMAT = 3  # 3: a zip of .npy leaves; 2: the same leaves in one msgpack message; 1: replay rows held the
#             observation features (2 on: one-hot indices, replay.OneHotCodec), never read
READABLE = (2, 3)


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used for this run (corrupt, another format, another shape)."""


def save(path: str | Path, tree, meta: dict) -> None:
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        with zipfile.ZipFile(f, "w", zipfile.ZIP_STORED) as z:
            z.writestr("meta.json", json.dumps({"format": FORMAT, "meta": meta}))
            for i, leaf in enumerate(jax.tree.leaves(tree)):
                with z.open(f"leaves/{i}.npy", "w", force_zip64=True) as out:
                    np.lib.format.write_array(out, np.asarray(leaf), allow_pickle=False)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_meta(path: str | Path) -> dict:
    with _Source(Path(path)) as source:
        return source.meta


def load(path: str | Path, like):
    """``(tree, meta)`` from ``path``; ``like``: a pytree of arrays or ShapeDtypeStructs to rebuild on."""
    want, treedef = jax.tree.flatten(like)
    with _Source(Path(path)) as source:
        if source.count != len(want):
            raise CheckpointError(f"{path}: holds {source.count} arrays, this run's state has {len(want)}")
        leaves = []
        for i, w in enumerate(want):
            x = source.leaf(i)
            if x.shape != tuple(w.shape) or x.dtype != w.dtype:
                raise CheckpointError(f"{path}: array {i} is {x.dtype}{list(x.shape)}, this run's state needs "
                                      f"{np.dtype(w.dtype)}{list(w.shape)}")
            leaves.append(x)
        return jax.tree.unflatten(treedef, leaves), source.meta


class _Source:
    """A checkpoint file's meta and leaves, read on demand (format 3) or from one message (format 2)."""

    def __init__(self, path: Path):
        self.path, self.zip, self.payload = path, None, None
        try:
            self.meta = self._check(self._head())
        except BaseException:
            self.close()
            raise

    def _head(self) -> dict:
        """The file's format and meta (and, for format 2, its whole payload); sets ``count``."""
        try:
            if zipfile.is_zipfile(self.path):
                self.zip = zipfile.ZipFile(self.path)
                self.count = sum(name.startswith("leaves/") for name in self.zip.namelist())
                return json.loads(self.zip.read("meta.json"))
            head = self.payload = serialization.msgpack_restore(self.path.read_bytes())
            self.count = len(head.get("leaves", ())) if isinstance(head, dict) else 0
            return head
        except (OSError, ValueError, TypeError, KeyError, zipfile.BadZipFile) as err:
            raise CheckpointError(f"{self.path}: unreadable checkpoint ({err})") from None

    def _check(self, head) -> dict:
        if not isinstance(head, dict) or "format" not in head or "meta" not in head:
            raise CheckpointError(f"{self.path}: not a jaxusar checkpoint")
        if head["format"] not in READABLE:
            raise CheckpointError(
                f"{self.path}: a checkpoint of format {head['format']}, written by another jaxusar (this one reads "
                f"formats {', '.join(map(str, READABLE))}: replay rows store observations compactly since format "
                "2); it cannot be resumed, pass --force to start over")
        return head["meta"]

    def leaf(self, i: int) -> np.ndarray:
        try:
            if self.zip is None:
                return np.asarray(self.payload["leaves"][str(i)])
            with self.zip.open(f"leaves/{i}.npy") as f:
                return np.lib.format.read_array(f, allow_pickle=False)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as err:
            raise CheckpointError(f"{self.path}: unreadable checkpoint, array {i} ({err})") from None

    def close(self):
        if self.zip is not None:
            self.zip.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
