"""The learner protocol the trainer drives, and the DQN learner every Q-learning algorithm reuses.

A learner is a handful of pure, per-trial functions (the trainer vmaps them over trials):

``init(key, transition) -> state``           parameters, optimizer, replay (rows shaped like
                                             the example transition the trainer passes)
``init_carry() -> carry``                    per-episode actor state (e.g. DOC's current options)
``act(state, obs, carry, noise, step)``      -> (action, carry): exploring action for one env step
``observe(state, transition) -> state``      store what the update needs
``update(state, noise) -> state``            one learning step (every ``train_every`` env steps)
``policy(state) -> params``                  what a greedy test evaluates (snapshotted)
``greedy_act(params, obs, carry)``           -> (action, carry): the test policy
``action_shape``                             shape of the int32 action ``env.step`` takes
``act_noise`` / ``update_noise``             {name: shape} of the uniforms ``act``/``update`` consume;
                                             the trainer draws a whole chunk's worth at once.

A research fork adds a learner by writing one file in ``jaxusar/algos/`` that builds one of these.
"""

from __future__ import annotations

from typing import Callable, Protocol

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from jaxusar.config import ConfigError, DQNConfig
from jaxusar.core.qlearning import (MLP, NEG_INF, DQN, double_q_learning_target, epsilon_greedy, linear_epsilon,
                                    q_learning_target)


class Learner(Protocol):
    action_shape: tuple
    act_noise: dict
    update_noise: dict

    def init(self, key, transition: dict): ...
    def init_carry(self): ...
    def act(self, state, obs, carry, noise, step): ...
    def observe(self, state, transition: dict): ...
    def update(self, state, noise): ...
    def policy(self, state): ...
    def greedy_act(self, params, obs, carry): ...


def default_row(transition: dict) -> dict:
    """obs, action, reward, next_obs, whether the next state is terminal (the task solved, not a
    time-limit cut) and whether the episode ended (``done``, which stops an n-step return)."""
    return {"obs": transition["obs"], "action": transition["action"], "reward": transition["reward"],
            "next_obs": transition["next_obs"], "terminal": transition["info"]["terminated"],
            "done": transition["done"]}


def agent_axis(obs_shape: int | tuple, n_agents: int) -> bool:
    """Whether observations of shape ``obs_shape`` (an env's ``obs_shape``, or an int: a flat vector) hold
    one row per agent on a leading axis (``[n_agents, obs_dim]``, as the USAR world's ``view``) rather than
    one vector every agent sees (``[obs_dim]``). Any other shape is a ValueError."""
    shape = (obs_shape,) if isinstance(obs_shape, int) else tuple(obs_shape)
    if len(shape) == 1:
        return False
    if len(shape) == 2 and shape[0] == n_agents:
        return True
    raise ValueError(f"observation shape {shape}: expected [obs_dim] (one observation for all) or "
                     f"[{n_agents}, obs_dim] (one row per agent)")


def dqn_target(cfg: DQNConfig, valid_fn: Callable | None = None):
    """The DQN / Double-DQN target (``cfg.double_dqn``) r + discount * max_a q_t[a] of a replay batch:
    one rule for one-step, n-step and SMDP rows (they differ only in what ``sample_returns`` makes).

    ``reward``/``discount``/``next_obs`` are the batch's (n-step) return, bootstrap discount and
    observation (``replay.sample_returns``): bootstraps through time-limit truncations, only
    ``terminal`` (the task solved) stops it. ``valid_fn(next_obs) -> bool[A]``: the max ranges over
    the actions valid there (None: all).
    """

    def target(batch, q_t_target, q_t_online):
        valid_t = None if valid_fn is None else jax.vmap(valid_fn)(batch["next_obs"].astype(jnp.float32))
        if cfg.double_dqn:
            return double_q_learning_target(batch["reward"], batch["discount"], q_t_target, q_t_online, valid_t)
        return q_learning_target(batch["reward"], batch["discount"], q_t_target, valid_t)

    return target


class IndependentDQN:
    """``n`` DQNs with their own parameters, optimizers and replay buffers, acting side by side.

    Learner ``i`` picks ``action[i]``; nothing is shared (independent Q-learning, Tan 1993). It sees the
    whole observation, or, where the observation holds one row per agent (``obs_shape`` [n, obs_dim]:
    partial observability), its own row ``obs[i]``, and its replay rows store that row only. With
    ``n = 1`` it is a single-agent DQN (``action`` has shape [1]).

    Args:
      obs_shape: the observation's shape (``env.obs_shape``): [obs_dim], or [n, obs_dim] for one row per
        learner (``agent_axis``); an int is [obs_dim]. n_actions, n: sizes. cfg: DQNConfig.
      target_fn(batch, q_t_target, q_t_online) -> float[B]: the learner's target rule (see qlearning).
      row_fn(transition) -> dict: the replay row of learner-independent fields (defaults to
        ``default_row``); the trainer's transition has obs, action, reward, next_obs, done, info.
      valid_fn(obs) -> bool[n_actions]: actions allowed in ``obs`` (e.g. options whose initiation set
        holds; with one row per learner, ``obs`` is the learner's row); None = all. Random exploration
        only ever picks valid actions.
      mask_greedy: whether the greedy choice is restricted to valid actions too (False: the learner
        must learn validity itself, e.g. from a penalty).
      obs_blocks: the widths of the one-hot blocks the observation is made of (``env.obs_blocks``): replay
        rows then store one small integer per block (``replay.OneHotCodec``); None = one uint8 per feature.
    """

    def __init__(self, obs_shape: int | tuple, n_actions: int, n: int, cfg: DQNConfig, target_fn: Callable,
                 row_fn: Callable = default_row, valid_fn: Callable | None = None, mask_greedy: bool = True,
                 obs_blocks: tuple[int, ...] | None = None):
        self.per_agent = agent_axis(obs_shape, n)
        obs_dim = obs_shape if isinstance(obs_shape, int) else int(obs_shape[-1])
        self.dqn = DQN(obs_dim, n_actions, cfg, target_fn, obs_blocks)
        self.cfg, self.n, self.n_actions, self.obs_dim = cfg, n, n_actions, obs_dim
        self.row_fn, self.valid_fn, self.mask_greedy = row_fn, valid_fn, mask_greedy
        self.action_shape = (n,)
        self.act_noise = {"explore": (n,), "action": (n,)}
        self.update_noise = {"sample": (n, cfg.batch_size)}

    def _rows(self, transition: dict, params=None) -> dict:
        """The shared row, broadcast to every learner, with each learner's own action (and, with one
        observation row per learner, its own ``obs`` and ``next_obs`` rows) and, for n-step returns cut at
        exploring actions, whether that action was the greedy one under ``params`` (those it was chosen with)."""
        row = self.row_fn(transition)
        own = {k: row.pop(k) for k in ("obs", "next_obs") if self.per_agent and k in row}  # already [n, obs_dim]
        rows = jax.tree.map(lambda x: jnp.broadcast_to(x, (self.n, *jnp.shape(x))), row)
        rows.update(own)
        rows["action"] = transition["action"]
        if self.cfg.n_step > 1 and self.cfg.n_step_cut_exploring:  # see replay.sample_returns
            greedy = transition["action"] if params is None else \
                self.greedy_act(params, transition["obs"], transition["carry"])[0]
            rows["greedy"] = greedy == transition["action"]
        return rows

    def init(self, key, transition: dict):
        rows = self._rows(transition)
        return jax.vmap(self.dqn.init)(jax.random.split(key, self.n), rows)

    def init_carry(self):
        return jnp.zeros((), jnp.int32)

    def _q(self, params, obs):
        """float[n, A]: learner i's Q-values at the whole ``obs``, or at its own row ``obs[i]``."""
        return jax.vmap(self.dqn.q_values, in_axes=(0, 0 if self.per_agent else None))(params, obs)

    def _valid(self, obs):
        """None, bool[A] (one for every learner) or, with one row per learner, bool[n, A]."""
        if self.valid_fn is None:
            return None
        return jax.vmap(self.valid_fn)(obs) if self.per_agent else self.valid_fn(obs)

    def act(self, state, obs, carry, noise, step):
        eps = linear_epsilon(self.cfg, step)
        q, valid = self._q(state.params, obs), self._valid(obs)
        if self.per_agent and valid is not None:
            pick = lambda q_i, v_i, ue, ua: epsilon_greedy(q_i, eps, ue, ua, v_i, self.mask_greedy)
            return jax.vmap(pick)(q, valid, noise["explore"], noise["action"]), carry
        pick = lambda q_i, ue, ua: epsilon_greedy(q_i, eps, ue, ua, valid, self.mask_greedy)
        return jax.vmap(pick)(q, noise["explore"], noise["action"]), carry

    def observe(self, state, transition):
        return jax.vmap(self.dqn.add)(state, self._rows(transition, state.params))

    def update(self, state, noise):
        return jax.vmap(self.dqn.update)(state, noise["sample"])

    def policy(self, state):
        return state.params

    def greedy_act(self, params, obs, carry):
        q, valid = self._q(params, obs), self._valid(obs)
        if valid is not None and self.mask_greedy:
            q = jnp.where(valid, q, -jnp.inf)
        return jnp.argmax(q, axis=-1).astype(jnp.int32), carry


class FactoredDQN:
    """One Q-network whose output is ``n`` heads of ``n_actions``, summed: Q(s, a) = sum_i Q_i(s, a_i)
    (value decomposition, Sunehag et al. 2018), so parameters and compute grow linearly in ``n`` where
    a flat head over joint actions grows as ``n_actions ** n``.

    The action is int32[n], one per head; each head picks greedily (or explores) among its own valid
    actions, ``valid_fn(obs) -> bool[n, n_actions]``, which the greedy choice always respects. The
    target of a row is r + discount * sum_i max over head i's valid actions of Q_i^target(s', .): the
    max of the sum over the valid joint actions, since validity factors per head. ``cfg.double_dqn``
    is not supported.

    Args as ``IndependentDQN``'s, with ``n`` the number of heads, which share one replay.
    """

    def __init__(self, obs_dim: int, n_actions: int, n: int, cfg: DQNConfig, valid_fn: Callable,
                 row_fn: Callable = default_row, obs_blocks: tuple[int, ...] | None = None):
        if cfg.double_dqn:
            raise ValueError("FactoredDQN: double_dqn is not supported")
        self.cfg, self.n, self.n_actions, self.obs_dim = cfg, n, n_actions, obs_dim
        self.row_fn, self.valid_fn = row_fn, valid_fn
        self.dqn = DQN(obs_dim, n * n_actions, cfg, self._target, obs_blocks, action_value=self._joint_value)
        self.action_shape = (n,)
        self.act_noise = {"explore": (n,), "action": (n,)}
        self.update_noise = {"sample": (cfg.batch_size,)}

    def _heads(self, q: jax.Array) -> jax.Array:
        return q.reshape(*q.shape[:-1], self.n, self.n_actions)

    def _joint_value(self, q: jax.Array, action: jax.Array) -> jax.Array:
        """float[B]: sum_i Q_i(s, a_i) of q float[B, n * n_actions] at actions int[B, n]."""
        return jnp.take_along_axis(self._heads(q), action[..., None].astype(jnp.int32), axis=-1)[..., 0].sum(-1)

    def _target(self, batch, q_t_target, q_t_online):
        valid_t = jax.vmap(self.valid_fn)(batch["next_obs"].astype(jnp.float32))
        best = jnp.where(valid_t, self._heads(q_t_target), NEG_INF).max(-1).sum(-1)
        return batch["reward"] + batch["discount"] * best

    def init(self, key, transition: dict):
        return self.dqn.init(key, self.row_fn(transition))

    def init_carry(self):
        return jnp.zeros((), jnp.int32)

    def act(self, state, obs, carry, noise, step):
        eps = linear_epsilon(self.cfg, step)
        q, valid = self._heads(self.dqn.q_values(state.params, obs)), self.valid_fn(obs)
        pick = lambda q_i, v_i, ue, ua: epsilon_greedy(q_i, eps, ue, ua, v_i)
        return jax.vmap(pick)(q, valid, noise["explore"], noise["action"]), carry

    def observe(self, state, transition):
        return self.dqn.add(state, self.row_fn(transition))

    def update(self, state, noise):
        return self.dqn.update(state, noise["sample"])

    def policy(self, state):
        return state.params

    def greedy_act(self, params, obs, carry):
        q = jnp.where(self.valid_fn(obs), self._heads(self.dqn.q_values(params, obs)), -jnp.inf)
        return jnp.argmax(q, axis=-1).astype(jnp.int32), carry


# -- value decomposition: agents' Q-values mixed into the team's ------------------------------------
@struct.dataclass
class TeamQ:
    """A ``TeamNetwork``'s output at observations with leading axes ``[...]``: everything the team's loss
    needs there, so ``DQN``'s ``action_value`` and ``target_fn`` hooks need no parameters of their own."""

    agents: jax.Array  # float[..., n, A]: each agent's Q-values at its observation
    state: jax.Array   # float[..., S]: what the mixer conditions on
    mixer: object      # the mixer's params, of whichever network (online or target) was applied


class TeamNetwork:
    """``n`` agents' Q-networks (one ``agent`` MLP each, params stacked on a leading agent axis, as
    ``IndependentDQN``'s) and a ``mixer``, with flax's ``init``/``apply``: ``apply(params, obs)`` is a ``TeamQ``.

    Agent ``i`` sees the whole observation, or its own row ``obs[..., i, :]`` where the observation holds
    one per agent; the mixer's state is the observation, or the agents' rows concatenated.
    ``mixer``: a flax module, ``mixer(q float[..., n], state float[..., S]) -> float[...]``.
    """

    def __init__(self, agent: nn.Module, mixer: nn.Module, n: int, per_agent: bool):
        self.agent, self.mixer, self.n, self.per_agent = agent, mixer, n, per_agent

    def state(self, obs: jax.Array) -> jax.Array:
        return obs.reshape(*obs.shape[:-2], -1) if self.per_agent else obs

    def init(self, key, obs: jax.Array) -> dict:
        """{"agents", "mixer"}; agent i's params are ``IndependentDQN``'s learner i's (the same keys)."""
        agents = jax.vmap(self.agent.init, in_axes=(0, None))(jax.random.split(key, self.n),
                                                               obs[0] if self.per_agent else obs)
        q = jnp.zeros((*obs.shape[:obs.ndim - 1 - self.per_agent], self.n), jnp.float32)
        return {"agents": agents, "mixer": self.mixer.init(jax.random.fold_in(key, self.n), q, self.state(obs))}

    def agent_q(self, agent_params, obs: jax.Array) -> jax.Array:
        """float[..., n, A]: every agent's Q-values (all a decentralised policy needs)."""
        return jax.vmap(self.agent.apply, in_axes=(0, -2 if self.per_agent else None), out_axes=-2)(agent_params, obs)

    def apply(self, params: dict, obs: jax.Array) -> TeamQ:
        return TeamQ(self.agent_q(params["agents"], obs), self.state(obs), params["mixer"])

    def mix(self, q: TeamQ, chosen: jax.Array) -> jax.Array:
        """float[...]: the team's Q from each agent's value ``chosen`` float[..., n] (at ``q``'s state)."""
        return self.mixer.apply(q.mixer, chosen, q.state)


class TeamDQN:
    """Value decomposition: ``n`` agents' Q-networks whose values at their actions a ``mixer`` combines into
    the team's, Q_tot(s, a) = mixer(Q_1(o_1, a_1), ..., Q_n(o_n, a_n); s), fitted to the team reward by one
    TD loss on one team replay (VDN: a sum, Sunehag et al. 2018; QMIX: a monotonic network of the state,
    Rashid et al. 2018).

    Each agent has its own parameters (no sharing, as ``IndependentDQN``), acts epsilon-greedily on its own
    Q-values and greedily by their argmax: decentralised, which is the team's argmax exactly when the mixer
    is monotonic in every agent's value (dQ_tot/dQ_i >= 0; both VDN's and QMIX's are). For the same reason the
    target is r + discount * mixer^target(max_a Q_i^target(o'_i, a); s') (Double DQN, ``cfg.double_dqn``: at
    the online agents' argmax), the bootstrap through time limits and n-step returns as ``dqn_target``'s.
    One optimizer over all parameters; the policy (what a greedy test runs, and kept as the best params) is
    the agents' networks only. The row is the team's: obs ([obs_dim], or [n, obs_dim] with one row per
    agent), action int32[n], the team reward. ``dqn.n_step_cut_greedy`` is not supported.

    Args as ``IndependentDQN``'s; ``mixer``: see ``TeamNetwork``.
    """

    def __init__(self, obs_shape: int | tuple, n_actions: int, n: int, cfg: DQNConfig, mixer: nn.Module,
                 row_fn: Callable = default_row, obs_blocks: tuple[int, ...] | None = None):
        if cfg.n_step > 1 and cfg.n_step_cut_greedy:
            raise ConfigError("dqn.n_step_cut_greedy is not supported by value decomposition (vdn, qmix); "
                              "dqn.n_step_cut_exploring is")
        self.per_agent = agent_axis(obs_shape, n)
        obs_dim = obs_shape if isinstance(obs_shape, int) else int(obs_shape[-1])
        self.cfg, self.n, self.n_actions, self.obs_dim, self.row_fn = cfg, n, n_actions, obs_dim, row_fn
        agent = MLP(tuple(cfg.hidden), n_actions, tuple(obs_blocks) if cfg.one_hot_input and obs_blocks else None)
        self.network = TeamNetwork(agent, mixer, n, self.per_agent)
        self.dqn = DQN(obs_dim, n_actions, cfg, self._target, obs_blocks, action_value=self._team_value,
                       network=self.network, input_shape=(n, obs_dim) if self.per_agent else (obs_dim,))
        self.action_shape = (n,)
        self.act_noise = {"explore": (n,), "action": (n,)}
        self.update_noise = {"sample": (cfg.batch_size,)}

    def _team_value(self, q: TeamQ, action: jax.Array) -> jax.Array:
        """float[B]: Q_tot at the taken joint actions int[B, n]."""
        chex.assert_rank([q.agents, action], [3, 2])
        return self.network.mix(q, jnp.take_along_axis(q.agents, action[..., None].astype(jnp.int32), -1)[..., 0])

    def _target(self, batch, q_t_target: TeamQ, q_t_online: TeamQ) -> jax.Array:
        if self.cfg.double_dqn:
            a_t = jnp.argmax(q_t_online.agents, -1)
            best = jnp.take_along_axis(q_t_target.agents, a_t[..., None], -1)[..., 0]
        else:
            best = q_t_target.agents.max(-1)
        return batch["reward"] + batch["discount"] * self.network.mix(q_t_target, best)

    def _row(self, transition: dict, params=None) -> dict:
        row = self.row_fn(transition)
        if self.cfg.n_step > 1 and self.cfg.n_step_cut_exploring:  # the joint action was the greedy one
            greedy = transition["action"] if params is None else \
                self.greedy_act(self.policy_of(params), transition["obs"], transition["carry"])[0]
            row["greedy"] = jnp.all(greedy == transition["action"])
        return row

    def init(self, key, transition: dict):
        return self.dqn.init(key, self._row(transition))

    def init_carry(self):
        return jnp.zeros((), jnp.int32)

    def act(self, state, obs, carry, noise, step):
        eps = linear_epsilon(self.cfg, step)
        pick = lambda q_i, ue, ua: epsilon_greedy(q_i, eps, ue, ua)
        q = self.network.agent_q(self.policy(state), obs)
        return jax.vmap(pick)(q, noise["explore"], noise["action"]), carry

    def observe(self, state, transition):
        return self.dqn.add(state, self._row(transition, state.params))

    def update(self, state, noise):
        return self.dqn.update(state, noise["sample"])

    @staticmethod
    def policy_of(params: dict):
        return params["agents"]

    def policy(self, state):
        return self.policy_of(state.params)

    def greedy_act(self, params, obs, carry):
        return jnp.argmax(self.network.agent_q(params, obs), axis=-1).astype(jnp.int32), carry
