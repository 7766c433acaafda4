"""Atomic run checkpoints: one pytree (a trainer's whole state) and a small metadata dict per file.

A checkpoint is written to ``<path>.tmp``, flushed to disk, then renamed over ``<path>`` (a rename is
atomic on POSIX), so a run killed at any moment leaves either the previous checkpoint or the new one,
never half of one. The pytree is stored as its flat list of leaves (msgpack, via flax.serialization);
``load`` rebuilds it on the structure of a template (e.g. ``jax.eval_shape`` of the trainer's init)
and refuses a file whose leaves do not match the template's shapes and dtypes.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax
import numpy as np
from flax import serialization

FORMAT = 2  # 2: replay rows hold observations as one-hot indices (replay.OneHotCodec); 1 held the features


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used for this run (corrupt, another format, another shape)."""


def save(path: str | Path, tree, meta: dict) -> None:
    path = Path(path)
    leaves = [np.asarray(x) for x in jax.device_get(jax.tree.leaves(tree))]
    payload = {"format": FORMAT, "meta": meta, "leaves": {str(i): x for i, x in enumerate(leaves)}}
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(serialization.msgpack_serialize(payload))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_meta(path: str | Path) -> dict:
    return _read(path)["meta"]


def load(path: str | Path, like):
    """``(tree, meta)`` from ``path``; ``like``: a pytree of arrays or ShapeDtypeStructs to rebuild on."""
    payload = _read(path)
    want, treedef = jax.tree.flatten(like)
    got = payload["leaves"]
    if len(got) != len(want):
        raise CheckpointError(f"{path}: holds {len(got)} arrays, this run's state has {len(want)}")
    leaves = []
    for i, w in enumerate(want):
        x = np.asarray(got[str(i)])
        if x.shape != tuple(w.shape) or x.dtype != w.dtype:
            raise CheckpointError(f"{path}: array {i} is {x.dtype}{list(x.shape)}, this run's state needs "
                                  f"{np.dtype(w.dtype)}{list(w.shape)}")
        leaves.append(x)
    return jax.tree.unflatten(treedef, leaves), payload["meta"]


def _read(path) -> dict:
    try:
        payload = serialization.msgpack_restore(Path(path).read_bytes())
    except (OSError, ValueError, TypeError) as err:
        raise CheckpointError(f"{path}: unreadable checkpoint ({err})") from None
    if not isinstance(payload, dict) or "format" not in payload:
        raise CheckpointError(f"{path}: not a jaxusar checkpoint")
    if payload["format"] != FORMAT:
        raise CheckpointError(f"{path}: a checkpoint of format {payload['format']}, written by another jaxusar "
                              f"(this one reads format {FORMAT}: replay rows store observations compactly since "
                              "format 2); it cannot be resumed, pass --force to start over")
    return payload
