"""A functional replay buffer: pure init / add / sample / can_sample on a pytree of rows.

Fixed capacity, overwrite-oldest, works under jit and vmap. Sampling takes pre-drawn uniforms
instead of a PRNG key, so a trainer can draw a whole chunk's randomness in one call (DESIGN.md:
per-step key splitting costs ~9% of update time on CPU).

We do not use flashbax here, on purpose (it was tried first; see benchmarks/README.md): its item
buffer samples with a key per call, and its trajectory buffer pairs ``o_t`` with the next stored row,
which crosses episode boundaries at resets and loses the true next observation at a time-limit
truncation. A row here is a whole transition (obs and next_obs stored together), so the next
observation is exact by construction.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


MAX_DECODE_RUNS = 64  # OneHotCodec.decode: runs of equal-width blocks it decodes one op each


class OneHotCodec:
    """Observations made of one-hot blocks, stored as one small integer per block (lossless).

    ``sizes``: the widths of the blocks, in order. A block's code is the index of its 1 (its width if it
    has none; a block may hold at most one 1), and a block of width 1 is a flag whose code is its value.
    ``encode`` maps float/uint8[..., sum(sizes)] to codes uint8[..., n_blocks] (uint16 if a block is wider
    than 255); ``decode`` rebuilds float32 exactly. A replay row then holds a medic's row, column and
    facing in 3 bytes instead of H + W + 4. The env's ``encoding="codes"`` observations are these codes.
    """

    def __init__(self, sizes):
        self.sizes = tuple(int(s) for s in sizes)
        if not self.sizes or min(self.sizes) < 1:
            raise ValueError(f"one-hot block sizes must be >= 1, got {self.sizes}")
        self.dim = sum(self.sizes)
        self.dtype = jnp.uint8 if max(self.sizes) < 256 else jnp.uint16
        # Static index tables, so that encode and decode are a few array ops whatever the number of blocks
        # (a map's observation may hold hundreds: one op per block made XLA compiles take minutes).
        sizes = np.asarray(self.sizes)
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        self._block_of = np.repeat(np.arange(len(sizes)), sizes)             # feature -> its block
        # feature -> the code that sets it: its place in the block, or 1 for a flag
        self._place = np.where(sizes[self._block_of] == 1, 1, np.arange(self.dim) - offsets[self._block_of])
        self._groups = []  # per block width: (the blocks of that width, their features [blocks, width])
        for size in np.unique(sizes):
            blocks = np.flatnonzero(sizes == size)
            self._groups.append((int(size), blocks, offsets[blocks][:, None] + np.arange(size)))
        self._order = np.argsort(np.concatenate([blocks for _, blocks, _ in self._groups]), kind="stable")
        # Runs of consecutive blocks of one width, [(first block, end, width)]: decode one-hots each run whole
        # (a compare with an iota), where a gather of every feature from its block costs 3-4x more on CPU.
        starts = np.flatnonzero(np.diff(sizes, prepend=0))
        self._runs = [(int(a), int(b), int(sizes[a])) for a, b in zip(starts, [*starts[1:], len(sizes)])]

    def encode(self, obs: jax.Array) -> jax.Array:
        obs = jnp.asarray(obs)
        if obs.shape[-1] != self.dim:
            raise ValueError(f"observation of width {obs.shape[-1]}, the one-hot blocks {self.sizes} sum to {self.dim}")
        code = lambda block, size: block[..., 0].astype(jnp.int32) if size == 1 else \
            jnp.where(block.any(-1), jnp.argmax(block, -1), size)
        offsets = np.concatenate([[0], np.cumsum(self.sizes)])
        # Few blocks: each sliced on its own (fastest: a sub-policy's 760-wide row, 1.4x faster than the runs
        # below). Many: each run of equal-width blocks sliced and reshaped (no gather, one op per run); the
        # most: one gather per width (a gather costs ~2 ns per feature on CPU, but keeps the program small).
        if len(self.sizes) <= MAX_DECODE_RUNS:
            return jnp.stack([code(obs[..., offsets[b]:offsets[b + 1]] > 0, size) for b, size in enumerate(self.sizes)],
                             -1).astype(self.dtype)
        hot = obs > 0
        if len(self._runs) <= MAX_DECODE_RUNS:
            blocks = [hot[..., offsets[a]:offsets[b]].reshape(*hot.shape[:-1], b - a, size) for a, b, size in self._runs]
            return jnp.concatenate([code(block, size) for block, (_, _, size) in zip(blocks, self._runs)],
                                   -1).astype(self.dtype)
        codes = []
        for size, _, features in self._groups:  # the index of each block's first 1, its width where it has none
            codes.append(code(hot[..., features], size))  # features [blocks, size]
        return jnp.concatenate(codes, -1)[..., self._order].astype(self.dtype)

    def decode(self, codes: jax.Array | list) -> jax.Array:
        """float32[..., dim] of codes [..., n_blocks], or of a list of code arrays that concatenate to them
        (each then decoded where it lies: XLA fuses a concatenation of integers before the compares poorly)."""
        segments = [jnp.asarray(c).astype(jnp.int32) for c in (codes if isinstance(codes, (list, tuple)) else [codes])]
        if sum(c.shape[-1] for c in segments) != len(self.sizes):
            raise ValueError(f"{sum(c.shape[-1] for c in segments)} codes for {len(self.sizes)} blocks")
        if len(self._runs) + len(segments) > MAX_DECODE_RUNS:  # many short runs: one gather keeps the program small
            whole = jnp.concatenate(segments, -1)
            return (whole[..., self._block_of] == self._place).astype(jnp.float32)
        parts, start = [], 0
        for seg in segments:
            end = start + seg.shape[-1]
            for a, b, size in self._runs:  # the part of each run of equal-width blocks in this segment
                lo, hi = max(a, start), min(b, end)
                if lo < hi:
                    run = seg[..., lo - start:hi - start, None] == (np.ones(1) if size == 1 else np.arange(size))
                    # each run cast on its own: a cast after the concatenation fuses worse
                    parts.append(run.astype(jnp.float32).reshape(*seg.shape[:-1], (hi - lo) * size))
            start = end
        return jnp.concatenate(parts, -1)


@struct.dataclass
class Replay:
    """rows: pytree whose leaves have a leading [capacity] axis; pos: next write slot; size: filled rows."""

    rows: object
    pos: jax.Array
    size: jax.Array

    @property
    def capacity(self) -> int:
        return jax.tree.leaves(self.rows)[0].shape[0]


def row_bytes(buffer: Replay) -> int:
    """Bytes one stored row takes (``buffer`` may carry leading lane axes, or be ``jax.eval_shape`` shapes)."""
    lead = len(buffer.pos.shape) + 1  # the lane axes, then the capacity axis
    return sum(np.dtype(x.dtype).itemsize * math.prod(x.shape[lead:]) for x in jax.tree.leaves(buffer.rows))


def init(example_row, capacity: int) -> Replay:
    """An empty buffer whose rows look like ``example_row`` (shapes and dtypes are kept exactly)."""
    rows = jax.tree.map(lambda x: jnp.zeros((capacity, *jnp.shape(x)), jnp.asarray(x).dtype), example_row)
    return Replay(rows=rows, pos=jnp.zeros((), jnp.int32), size=jnp.zeros((), jnp.int32))


def add(buffer: Replay, row) -> Replay:
    """Write one row at ``pos`` (overwriting the oldest once full)."""
    rows = jax.tree.map(lambda store, x: store.at[buffer.pos].set(jnp.asarray(x, store.dtype)), buffer.rows, row)
    return Replay(rows=rows, pos=(buffer.pos + 1) % buffer.capacity,
                  size=jnp.minimum(buffer.size + 1, buffer.capacity))


def can_sample(buffer: Replay, batch_size: int) -> jax.Array:
    return buffer.size >= batch_size


def _indices(buffer: Replay, u: jax.Array) -> jax.Array:
    return jnp.minimum((u * buffer.size).astype(jnp.int32), jnp.maximum(buffer.size - 1, 0))


def sample(buffer: Replay, u: jax.Array):
    """Rows at indices floor(u * size), uniformly over the filled slots. ``u`` float[batch] in [0, 1)."""
    idx = _indices(buffer, u)
    return jax.tree.map(lambda store: store[idx], buffer.rows)


def sample_returns(buffer: Replay, u: jax.Array, n: int, extend=None):
    """Rows drawn as ``sample``, each with its n-step return (Sutton and Barto 2018, Sec. 7.1).

    The rows of one learner are written in time order, so row ``i``'s successors are ``i + 1, ...``.
    Each needs ``reward``, ``gamma`` (its own discount: gamma, or gamma^k for an SMDP step),
    ``terminal`` (the task ended: no bootstrap), ``done`` (the episode ended, by termination or a time
    limit) and ``next_obs``. The return runs over m <= n rows: it stops after the first row whose
    episode ended and at the newest row written, so it never crosses into another episode::

        reward   = sum_{j<m} (prod_{l<j} gamma_l) r_j
        discount = prod_{j<m} gamma_j, times 0 if row m-1 is terminal
        next_obs = next_obs of row m-1

    A time-limit cut (done, not terminal) keeps its bootstrap from the true next observation stored
    in that row. With n = 1 this is row i itself with discount gamma * (1 - terminal).

    ``extend(k int32[B]) -> bool[B]``, optional: whether the return may go on through row ``k`` (a
    successor, never the row itself). The DQN core passes "row k's action is the greedy one", the
    greedy policy of the acting params (``dqn.n_step_cut_exploring``) or of the current target net
    (``dqn.n_step_cut_greedy``): Watkins's Q(lambda) cut (Sutton and Barto 2018, Sec. 12.10), so the
    return estimates the greedy policy's value, Q*, and not the exploring policy's (measured in
    benchmarks/README.md).
    """
    idx = _indices(buffer, u)
    rows, cap = buffer.rows, buffer.capacity
    batch = jax.tree.map(lambda store: store[idx], rows)
    newer = (buffer.pos - 1 - idx) % cap  # rows written after row i
    ret = jnp.zeros(idx.shape, jnp.float32)
    discount = jnp.ones(idx.shape, jnp.float32)
    alive, last = jnp.ones(idx.shape, bool), idx
    for j in range(n):
        k = (idx + j) % cap
        take = alive & (j <= newer)
        if j > 0 and extend is not None:
            take = take & extend(k)
        ret = jnp.where(take, ret + discount * rows["reward"][k], ret)
        discount = jnp.where(take, discount * rows["gamma"][k] * (1.0 - rows["terminal"][k].astype(jnp.float32)),
                             discount)
        last = jnp.where(take, k, last)
        alive = take & ~rows["done"][k] & ~rows["terminal"][k]
    batch.update(reward=ret, discount=discount, next_obs=rows["next_obs"][last])
    return batch
