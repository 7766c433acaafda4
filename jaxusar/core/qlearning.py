"""The one Q-learning update every learner in jaxusar uses (IQL, sub-policies, coordinator, DOC critic).

Target rules are small pure functions of named tensors (rlax style: ``_tm1`` is the step the action
was taken in, ``_t`` the step after). A learner picks its rule by passing a ``target_fn`` to
``DQN``; the replay, the loss, the optimizer and the target network are shared.

Every target is ``r + discount * max_a q_t[a]`` over a replay batch from ``replay.sample_returns``:
``r`` the (n-step) return and ``discount`` its bootstrap discount, so the one-step, n-step and SMDP
targets are one rule; they differ only in the rows (an SMDP row's own discount is gamma^k, Sutton,
Precup and Singh 1999, eq. 8).

Sources: Mnih et al. 2015 (DQN, target network); van Hasselt et al. 2016 (Double DQN); Hessel et al.
2018 (n-step returns, Rainbow); Fedus et al. 2020 (replay ratio).
"""

from __future__ import annotations

from typing import Callable, Sequence

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from jaxusar.config import DQNConfig
from jaxusar.core import replay as rb

NEG_INF = -1e9


# -- target rules ---------------------------------------------------------------------------------
def q_learning_target(r_t: jax.Array, discount_t: jax.Array, q_t: jax.Array,
                      valid_t: jax.Array | None = None) -> jax.Array:
    """One-step Q-learning target r_t + discount_t * max_a q_t[a] (max over valid actions).

    r_t float[B]; discount_t float[B] (gamma, or 0 at a terminal step); q_t float[B, A] from the target
    network; valid_t optional bool[B, A].
    """
    chex.assert_rank([r_t, discount_t, q_t], [1, 1, 2])
    if valid_t is not None:
        q_t = jnp.where(valid_t, q_t, NEG_INF)
    return r_t + discount_t * jnp.max(q_t, axis=-1)


def double_q_learning_target(r_t, discount_t, q_t_value, q_t_selector, valid_t=None) -> jax.Array:
    """Double DQN: the online net selects argmax_a q_t_selector[a], the target net values it."""
    chex.assert_rank([r_t, discount_t, q_t_value, q_t_selector], [1, 1, 2, 2])
    if valid_t is not None:
        q_t_selector = jnp.where(valid_t, q_t_selector, NEG_INF)
    a_t = jnp.argmax(q_t_selector, axis=-1)
    return r_t + discount_t * jnp.take_along_axis(q_t_value, a_t[:, None], axis=-1)[:, 0]


# -- the shared DQN machinery -----------------------------------------------------------------------
class OneHotDense(nn.Module):
    """``nn.Dense`` on an input made of one-hot blocks (widths ``sizes``; a width-1 block is a flag), by
    looking up the kernel's rows at each block's 1 instead of multiplying the whole vector: the same
    function and parameters (names, shapes, init), at a cost per block instead of per feature."""

    features: int
    sizes: Sequence[int]

    @nn.compact
    def __call__(self, x):
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))
        codes = rb.OneHotCodec(self.sizes).encode(x).astype(jnp.int32)  # [..., blocks]
        sizes = np.asarray(self.sizes)
        offsets = jnp.asarray(np.cumsum((0,) + tuple(self.sizes[:-1])))
        flag = jnp.asarray(sizes == 1)
        rows = kernel[offsets + jnp.where(flag, 0, jnp.minimum(codes, jnp.asarray(sizes) - 1))]  # [..., blocks, features]
        hot = jnp.where(flag, codes == 1, codes < jnp.asarray(sizes))  # the block has a 1
        return jnp.sum(jnp.where(hot[..., None], rows, 0.0), axis=-2) + bias


class MLP(nn.Module):
    """A plain ReLU MLP mapping features float[..., D] to float[..., n_out]. With ``one_hot_blocks`` (the
    input's one-hot block widths) the first layer is a ``OneHotDense``: the same network, cheaper on wide
    one-hot inputs."""

    hidden: Sequence[int]
    n_out: int
    one_hot_blocks: Sequence[int] | None = None

    @nn.compact
    def __call__(self, x):
        for i, width in enumerate(self.hidden):
            layer = OneHotDense(width, self.one_hot_blocks, name="Dense_0") if i == 0 and self.one_hot_blocks \
                else nn.Dense(width, name=f"Dense_{i}")
            x = nn.relu(layer(x))
        return nn.Dense(self.n_out, name=f"Dense_{len(self.hidden)}")(x)


@struct.dataclass
class DQNState:
    params: object
    target_params: object
    opt_state: object
    replay: rb.Replay
    updates: jax.Array  # gradient updates done


def linear_epsilon(cfg: DQNConfig, step: jax.Array) -> jax.Array:
    """Linear decay from eps_start to eps_end over eps_decay_steps env steps, then flat."""
    frac = jnp.clip(step / cfg.eps_decay_steps, 0.0, 1.0)
    return cfg.eps_start + frac * (cfg.eps_end - cfg.eps_start)


def epsilon_greedy(q: jax.Array, eps: jax.Array, u_explore: jax.Array, u_action: jax.Array,
                   valid: jax.Array | None = None, mask_greedy: bool = True) -> jax.Array:
    """Greedy in q float[A] with probability 1 - eps, else uniform over the ``valid`` actions.

    ``mask_greedy`` (static): the greedy choice is restricted to ``valid`` too; False lets it pick any
    action (a learner that must learn validity itself). u_explore, u_action: uniforms in [0, 1).
    """
    n = q.shape[-1]
    if valid is None:
        valid = jnp.ones((n,), bool)
    greedy = jnp.argmax(jnp.where(valid, q, NEG_INF) if mask_greedy else q)
    # the (floor(u * n_valid))-th valid action
    rank = jnp.floor(u_action * valid.sum()).astype(jnp.int32)
    random = jnp.argmax(jnp.cumsum(valid) > rank)
    return jnp.where(u_explore < eps, random, greedy).astype(jnp.int32)


TargetFn = Callable[[dict, jax.Array, jax.Array], jax.Array]


def taken_value(q: jax.Array, action: jax.Array) -> jax.Array:
    """q float[B, A] at the taken actions int[B]: the value the loss fits (``DQN(action_value=...)``)."""
    return jnp.take_along_axis(q, action[:, None].astype(jnp.int32), axis=-1)[:, 0]


def learning_rate(cfg: DQNConfig):
    """The Adam step size: ``cfg.lr``, constant or decayed to ``cfg.lr_end`` over ``cfg.lr_decay_updates``
    gradient updates (linearly or along a cosine), then flat."""
    if cfg.lr_schedule == "linear":
        return optax.linear_schedule(cfg.lr, cfg.lr_end, cfg.lr_decay_updates)
    if cfg.lr_schedule == "cosine":
        return optax.cosine_decay_schedule(cfg.lr, cfg.lr_decay_updates, alpha=cfg.lr_end / cfg.lr)
    return cfg.lr


class DQN:
    """A Q-network with replay, target network and optimizer, as pure functions of a ``DQNState``.

    ``target_fn(batch, q_t_target, q_t_online) -> target float[B]`` states the learner's target
    rule; ``batch`` holds the replay rows (``obs``, ``action`` and whatever the learner stored) with
    ``reward``, ``discount`` and ``next_obs`` as ``replay.sample_returns`` makes them (``cfg.n_step``).
    ``action_value(q, action) -> float[B]`` is what the loss fits to the target: q at the taken action
    by default; a factored learner sums its heads' values.
    A row needs ``reward``, ``terminal``, ``done`` and ``next_obs``; its ``gamma`` defaults to
    ``cfg.gamma``; its reward is stored times ``cfg.reward_scale``. The learning rate follows
    ``cfg.lr_schedule`` over gradient updates.

    ``network`` (optional) replaces the MLP: any object with flax's ``init(key, x)`` / ``apply(params, x)``,
    initialised at zeros of ``input_shape`` (default [obs_dim]); its output at a batch of observations
    may be any pytree the learner's ``target_fn`` and ``action_value`` read (``learners.TeamDQN``: the
    agents' Q-values and what their mixer needs there).

    Observations (``obs``, ``next_obs``) are stored compactly: with ``obs_blocks`` (the widths of the
    one-hot blocks the env's features are made of, e.g. ``env.obs_blocks``) as one small integer per
    block (``replay.OneHotCodec``), rebuilt exactly inside the update; without, as uint8 (binary features).
    """

    def __init__(self, obs_dim: int, n_actions: int, cfg: DQNConfig, target_fn: TargetFn,
                 obs_blocks: tuple[int, ...] | None = None, action_value: Callable | None = None,
                 network=None, input_shape: tuple[int, ...] | None = None):
        self.cfg, self.obs_dim, self.n_actions = cfg, obs_dim, n_actions
        self.target_fn = target_fn
        self.action_value = action_value or taken_value
        self.codec = None if obs_blocks is None else rb.OneHotCodec(obs_blocks)
        if self.codec is not None and self.codec.dim != obs_dim:
            raise ValueError(f"obs_blocks {self.codec.sizes} sum to {self.codec.dim}, not obs_dim={obs_dim}")
        if cfg.one_hot_input and self.codec is None:
            raise ValueError("dqn.one_hot_input needs the observation's one-hot blocks (obs_blocks)")
        self.network = network if network is not None else \
            MLP(tuple(cfg.hidden), n_actions, self.codec.sizes if cfg.one_hot_input else None)
        self.input_shape = tuple(input_shape or (obs_dim,))
        self.optimizer = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(learning_rate(cfg)))

    def q_values(self, params, obs: jax.Array) -> jax.Array:
        return self.network.apply(params, obs.astype(jnp.float32))

    def init(self, key: jax.Array, example_row: dict) -> DQNState:
        params = self.network.init(key, jnp.zeros(self.input_shape, jnp.float32))
        row = self.compact(example_row)
        return DQNState(params=params, target_params=params, opt_state=self.optimizer.init(params),
                        replay=rb.init(row, self.cfg.buffer_capacity), updates=jnp.zeros((), jnp.int32))

    def compact(self, row: dict) -> dict:
        row = dict(row)
        if "done" not in row:
            raise ValueError("a replay row needs 'done' (the episode ended, time limits included) for n-step "
                             "returns not to cross episodes; see learners.default_row")
        row.setdefault("gamma", jnp.float32(self.cfg.gamma))
        if self.cfg.reward_scale != 1.0:
            row["reward"] = row["reward"] * self.cfg.reward_scale
        for k in ("obs", "next_obs"):
            row[k] = jnp.asarray(row[k]).astype(jnp.uint8) if self.codec is None else self.codec.encode(row[k])
        return row

    def decode(self, stored: jax.Array) -> jax.Array:
        """Stored observations -> the network's float32 input (``compact`` undone)."""
        return stored.astype(jnp.float32) if self.codec is None else self.codec.decode(stored)

    def expand(self, batch: dict) -> dict:
        """A sampled batch with its observations as the network's input."""
        return {**batch, "obs": self.decode(batch["obs"]), "next_obs": self.decode(batch["next_obs"])}

    def add(self, state: DQNState, row: dict) -> DQNState:
        return state.replace(replay=rb.add(state.replay, self.compact(row)))

    def loss(self, params, target_params, batch: dict, target_fn: TargetFn):
        q_tm1 = self.q_values(params, batch["obs"])
        q_t_target = self.q_values(target_params, batch["next_obs"])
        q_t_online = self.q_values(params, batch["next_obs"]) if self.cfg.double_dqn else q_t_target
        target = jax.lax.stop_gradient(target_fn(batch, q_t_target, q_t_online))
        td = self.action_value(q_tm1, batch["action"]) - target
        per = optax.huber_loss(td) if self.cfg.loss == "huber" else 0.5 * td ** 2
        return per.mean()

    def sample(self, state: DQNState, u_sample: jax.Array) -> dict:
        """A replay batch with its ``cfg.n_step`` returns, observations as the network's input."""
        rows, cfg = state.replay.rows, self.cfg
        extend = None
        if cfg.n_step > 1 and cfg.n_step_cut_exploring:  # greedy under the params that acted
            extend = lambda k: rows["greedy"][k]
        elif cfg.n_step > 1 and cfg.n_step_cut_greedy:  # greedy under the current target net

            def extend(k):
                q = self.q_values(state.target_params, self.decode(rows["obs"][k]))
                return jnp.argmax(q, axis=-1) == rows["action"][k].reshape(k.shape).astype(jnp.int32)
        return self.expand(rb.sample_returns(state.replay, u_sample, cfg.n_step, extend))

    def update(self, state: DQNState, u_sample: jax.Array, target_fn: TargetFn | None = None) -> DQNState:
        """One gradient step on a batch drawn with the uniforms u_sample float[batch_size].

        ``target_fn`` overrides the learner's rule for this call: a learner whose target depends on
        other parameters (option-critic's U uses the terminations) passes a closure over them.
        """
        batch = self.sample(state, u_sample)
        grads = jax.grad(self.loss)(state.params, state.target_params, batch, target_fn or self.target_fn)
        updates, opt_state = self.optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        n = state.updates + 1
        cfg = self.cfg
        if cfg.tau < 1.0:
            target = optax.incremental_update(params, state.target_params, cfg.tau)
        else:
            copy = (n % cfg.target_update_every) == 0
            target = jax.tree.map(lambda p, t: jnp.where(copy, p, t), params, state.target_params)
        return state.replace(params=params, target_params=target, opt_state=opt_state, updates=n)
