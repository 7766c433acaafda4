"""Simplified distributed option-critic (DOC), the paper's Sec. V baseline (Fig. 5): K options per medic.

Sources: Bacon, Harb and Precup 2017, "The Option-Critic Architecture" (intra-option policy gradient,
termination gradient, U); Chakravorty et al. 2019, "Option-Critic in Cooperative Multi-agent Systems"
(per-agent options and terminations, a centralized critic over joint options). The paper gives no
details beyond "centralized critic" and K in {2, 4, 8}; every choice below is ours, each a config value
in ``doc:`` (``jaxusar.config.DOCConfig``) where the sources differ.

Per agent i (two on the paper's map, any number N elsewhere): K intra-option policies pi_i(a | s, w_i)
(softmax over the 4 primitive actions) and K terminations beta_i(s, w_i) (sigmoid), one small MLP per
agent with a policy head (K x 4 logits) and a termination head (K logits) on a shared trunk
(``doc.actor_hidden``), its own Adam (``doc.actor_lr``). Every agent sees the full observation; where the
env gives each agent its own (``observation: view``, ``env.obs_shape`` [N, obs_dim]), agent i's actor
sees its own row and the centralized critic the joint observation, the N rows side by side.

**Critic.** Q(s, w1, w2), one MLP with K^2 outputs (joint option index w = w1 * K + w2; K^N for N
agents, agent 1 most significant), trained by the
shared ``core.qlearning.DQN`` (replay, target network, Huber loss, Adam; ``dqn:`` section) from
replay rows (obs, joint option w, primitive actions, reward, next_obs, terminal). Its target is the
option-critic U generalised to agents whose options end independently, with b_i = beta_i(s', w_i)
from the current actor and Q' the target network; for two agents::

    y = r + gamma (1 - terminal) U(s', w)
    U(s', w) = (1-b1)(1-b2) Q'(s', w1, w2)            neither option ends
             +    b1 (1-b2) max_v Q'(s', v, w2)       agent 1 re-chooses, agent 2's option fixed
             + (1-b1)    b2 max_v Q'(s', w1, v)       agent 2 re-chooses, agent 1's option fixed
             +    b1    b2  max_{v1,v2} Q'(s', v1, v2) both re-choose, jointly

and for N agents the sum over the 2^N sets of agents that re-choose, each max over their options with
the others' held (``option_critic_target``; with ``dqn.double_dqn`` the maxima are taken at the
online network's argmax). Time-limit cuts
bootstrap (only "all victims triaged" is terminal), as in IQL.

**Options.** An option in force at s_{t-1} ends at s_t with probability beta_i(s_t, w_i) (checked at
the start of ``act``, so the option used for the transition (s_t, a_t, s_{t+1}) is the one stored
in its replay row). A new option is chosen epsilon-greedily from the critic by the rule U assumes: one
agent's option ends -> argmax over its options with the other agent's option fixed; both end (and at
an episode's first step, where the carry holds NO_OPTION) -> the joint argmax (for N agents: the agents
whose options end re-choose jointly, the others' held). Epsilon follows the ``dqn.eps_*`` schedule
(the first re-choosing agent's draw decides); an exploring choice is uniform over each re-choosing
agent's K options.
Options change only at a termination.

**Actor losses** (per agent, summed; every critic value detached)::

    intra-option policy:  -log pi_i(a_i | s, w_i) (y - Q(s, w)) - entropy_weight H(pi_i(. | s, w_i))
    termination:          beta_i(s', w_i) (Q(s', w) - V_i(s') + xi)   (masked where s' is terminal)

with y the critic target above and V_i(s') the value of agent i re-choosing with the other agent's
option fixed. Gradient descent on the termination loss lowers beta where the current option's
advantage (+ xi) is positive and raises it where negative. Choices (config values):

* ``doc.value_baseline = max`` (default; V_i = max_v Q(s', v, w_-i), Bacon et al.'s greedy policy
  over options and the widely used implementations) or ``mean`` (mean over agent i's options, the
  value of a uniformly random re-choice).
* ``doc.termination_at = next`` (default; Bacon et al.'s termination gradient theorem, beta and the
  advantage at s', where the termination is actually sampled) or ``current`` (at s, as some
  implementations do). The online critic gives Q(s', .) here, the target network only gives U.
* ``doc.xi = 0.01`` and ``doc.entropy_weight = 0.01``: the sources' values, kept although the team
  reward here is 100 per victim (so both are small next to the advantages; we report what that does
  rather than tune it away).
* ``doc.actor_data = recent`` (default): the actor steps on the ``dqn.train_every`` newest
  transitions, so each transition drives exactly one actor step and the policy gradient is on-policy
  up to ``train_every`` steps of staleness (the common option-critic implementations take one actor
  step per env step on the latest transition). ``replay``: the actor steps on the critic's replay
  batch (the very rows the critic's update draws: sampling is a pure function of the same uniforms),
  the "simplified" off-policy variant: no importance weights, so the policy gradient is biased toward
  old behaviour. Measured on two_rooms (K = 2, 8 trials, 1500 episodes, otherwise the defaults): with
  ``recent`` the mean training return rose from 16 to 57 per episode (first vs last 300 episodes)
  and 6 of 8 trials' greedy tests triaged a victim; with ``replay`` it fell from 14 to 6, 1 of 8,
  and each actor step costs 4x the rows (the critic's batch of 32, not 8).
* The critic and the actor step simultaneously from the same parameters: y for the actor and U for
  the critic both use the pre-update actor and target network.

**Greedy test** (paper Fig. 5b, "greedy-Q"): options by the argmax rules above with no exploration,
each intra-option policy's most likely action, and an option ends where beta >= ``doc.greedy_termination``.

The critic has K^N outputs: 4,096 for 8 options and 4 medics, so this baseline stays a flat critic.
"""

from __future__ import annotations

import itertools
import math
from typing import Sequence

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from jaxusar.config import ConfigError, DOCConfig, DQNConfig
from jaxusar.core import replay as rb
from jaxusar.core.learners import agent_axis
from jaxusar.core.qlearning import DQN, DQNState, linear_epsilon
from jaxusar.envs import N_ACTIONS, USAREnv

ALGORITHM = "doc"  # `jaxusar train doc`: one run per number of options (doc.options)
EXPERIMENT = "jaxusar.experiments.doc"
NO_OPTION = -1

# The paper's run (Sec. V, Fig. 5): 5000 training episodes, a greedy test every 50, horizon 300
# (the EnvConfig default), K = 2, 4, 8. configs/doc.yaml spells out exactly these settings.
DEFAULTS = {
    "env": {"horizon": 300},
    "train": {"episodes": 5000, "test_every": 50},
    "dqn": {"hidden": [32, 32], "batch_size": 32, "train_every": 8},
    "doc": {"options": [2, 4, 8], "actor_hidden": [32, 32], "actor_lr": 5e-4, "entropy_weight": 0.01,
            "xi": 0.01, "value_baseline": "max", "termination_at": "next", "actor_data": "recent"},
}


# -- the math, one pure function per equation -----------------------------------------------------
def _best(q_value: jax.Array, q_select: jax.Array) -> jax.Array:
    """q_value at the argmax of q_select along the last axis."""
    a = jnp.argmax(q_select, axis=-1)
    return jnp.take_along_axis(q_value, a[..., None], axis=-1)[..., 0]


def _others_fixed(q: jax.Array, w: jax.Array, free: tuple[int, ...]) -> jax.Array:
    """Q(s, .) with every agent not in ``free`` held at its option in w: float[B, K^len(free)].

    q float[B, K, ..., K] (one axis per agent); w int[B, N]; free: agents whose option varies (static).
    """
    index = (jnp.arange(q.shape[0]),) + tuple(slice(None) if i in free else w[:, i] for i in range(w.shape[1]))
    return q[index].reshape(q.shape[0], -1)  # the batch axis first (NumPy's rule), then the free agents'


def option_critic_target(r_t: jax.Array, discount_t: jax.Array, q_t: jax.Array, beta_t: jax.Array,
                         w_tm1: jax.Array, q_t_selector: jax.Array | None = None) -> jax.Array:
    """y = r_t + discount_t U(s_t, w_tm1) for N agents (Bacon et al. 2017 eq. for U, generalised).

    U sums over every set T of agents whose options end (2^N terms): the probability
    prod_{i in T} b_i prod_{i not in T} (1 - b_i) times max over T's options, the others' held.
    r_t float[B]; discount_t float[B] (gamma, 0 at a terminal s_t); q_t float[B, K, ..., K] Q(s_t, w)
    from the target network; beta_t float[B, N] beta_i(s_t, w_tm1[i]); w_tm1 int[B, N] the options in
    force for the transition; q_t_selector optional, shaped as q_t, choosing the maxima (Double DQN).
    """
    n = w_tm1.shape[1]
    chex.assert_rank([r_t, discount_t, beta_t, w_tm1], [1, 1, 2, 2])
    chex.assert_rank(q_t, n + 1)
    sel = q_t if q_t_selector is None else q_t_selector
    u = 0.0
    for ends in range(2 ** n):  # bit i: agent i's option ends
        free = tuple(i for i in range(n) if ends >> i & 1)
        weight = 1.0
        for i in range(n):
            weight = weight * (beta_t[:, i] if i in free else 1 - beta_t[:, i])
        u = u + weight * _best(_others_fixed(q_t, w_tm1, free), _others_fixed(sel, w_tm1, free))
    return r_t + discount_t * u


def termination_advantage(q: jax.Array, w: jax.Array, baseline: str = "max") -> jax.Array:
    """A_i(s, w) = Q(s, w) - V_i(s), V_i over agent i's options with the others' fixed.

    q float[B, K, ..., K]; w int[B, N]; baseline "max" or "mean". Returns float[B, N].
    """
    n = w.shape[1]
    chex.assert_rank([q, w], [n + 1, 2])
    reduce = jnp.max if baseline == "max" else jnp.mean
    stay = _others_fixed(q, w, ())[:, 0]
    return jnp.stack([stay - reduce(_others_fixed(q, w, (i,)), axis=-1) for i in range(n)], axis=-1)


def termination_loss(beta: jax.Array, advantage: jax.Array, xi: float, mask: jax.Array) -> jax.Array:
    """Bacon et al.'s termination gradient as a loss: mean of beta (A + xi) over unmasked rows.

    beta float[B] (differentiable); advantage float[B] (detached by the caller); mask float[B].
    Descent lowers beta where A + xi > 0 (keep a good option) and raises it where A + xi < 0.
    """
    chex.assert_rank([beta, advantage, mask], [1, 1, 1])
    return jnp.mean(beta * jax.lax.stop_gradient(advantage + xi) * mask)


def intra_option_pg_loss(logits: jax.Array, a: jax.Array, advantage: jax.Array,
                         entropy_weight: float) -> jax.Array:
    """-log pi(a | s, w) A - entropy_weight H(pi(. | s, w)), averaged over the batch.

    logits float[B, A] of the option in force; a int[B] the action taken; advantage float[B] detached.
    """
    chex.assert_rank([logits, a, advantage], [2, 1, 1])
    logp = jax.nn.log_softmax(logits)
    logp_a = jnp.take_along_axis(logp, a[:, None].astype(jnp.int32), axis=-1)[:, 0]
    entropy = -jnp.sum(jnp.exp(logp) * logp, axis=-1)
    return jnp.mean(-logp_a * jax.lax.stop_gradient(advantage) - entropy_weight * entropy)


def sample_categorical(probs: jax.Array, u: jax.Array) -> jax.Array:
    """Inverse-CDF draw from probs float[..., A] with uniforms u float[...] in [0, 1)."""
    cdf = jnp.cumsum(probs, axis=-1)
    return jnp.minimum(jnp.sum(cdf <= u[..., None], axis=-1), probs.shape[-1] - 1).astype(jnp.int32)


# -- networks and state ------------------------------------------------------------------------------
class OptionActor(nn.Module):
    """One agent's options: obs float[..., D] -> (policy logits [..., K, A], termination logits [..., K])."""

    hidden: Sequence[int]
    n_options: int
    n_actions: int

    def setup(self):
        self.trunk = [nn.Dense(width) for width in self.hidden]
        self.policy = nn.Dense(self.n_options * self.n_actions)
        self.termination = nn.Dense(self.n_options)

    def features(self, x):
        for layer in self.trunk:
            x = nn.relu(layer(x))
        return x

    def __call__(self, x):
        h = self.features(x)
        logits = self.policy(h).reshape(*h.shape[:-1], self.n_options, self.n_actions)
        return logits, self.termination(h)

    def terminations(self, x):
        """Termination logits only (the critic's target needs no policy head)."""
        return self.termination(self.features(x))


@struct.dataclass
class DOCState:
    critic: DQNState    # centralized Q(s, w1, ..., wN): params, target, optimizer, replay
    actor: object       # per-agent OptionActor params, leading [n_agents] axis
    actor_opt: object


def _critic_needs_actor(batch, q_t_target, q_t_online):
    raise TypeError("the option-critic critic's target needs the terminations: "
                    "call DQN.update with the target_fn from OptionCritic.critic_target")


class OptionCritic:
    """The learner (protocol in ``jaxusar.core.learners``), for ``n_options`` = K options per agent.

    ``obs_shape``: the env's (an int: a flat vector every agent sees); [N, obs_dim] gives each actor its
    own row and the critic the rows side by side (``joint_obs``), which is what replay rows store."""

    def __init__(self, obs_shape: int | tuple, n_actions: int, n_options: int, cfg: DQNConfig, doc: DOCConfig,
                 obs_blocks: tuple[int, ...] | None = None, n_agents: int = 2):
        self.n_agents = n = int(n_agents)
        self.per_agent = agent_axis(obs_shape, n)
        self.obs_dim = obs_shape if isinstance(obs_shape, int) else int(obs_shape[-1])  # one actor's input
        self.n_actions, self.n_options = n_actions, int(n_options)
        self.cfg, self.doc = cfg, doc
        if cfg.n_step != 1:
            raise ConfigError(f"dqn.n_step={cfg.n_step}: option-critic's U target is one-step (the options in "
                              "force may change at every step); use dqn.n_step=1")
        critic_dim, critic_blocks = self.obs_dim, obs_blocks
        if self.per_agent:
            critic_dim, critic_blocks = n * self.obs_dim, None if obs_blocks is None else tuple(obs_blocks) * n
        self.critic = DQN(critic_dim, self.n_options ** n, cfg, _critic_needs_actor, critic_blocks)
        # joint index -> options, agent 0 most significant
        self.coords = np.array(list(itertools.product(range(self.n_options), repeat=n)), np.int32)
        self.actor_net = OptionActor(tuple(doc.actor_hidden), self.n_options, n_actions)
        self.actor_optimizer = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(doc.actor_lr))
        self.action_shape = (n,)
        self.act_noise = {"terminate": (n,), "option_explore": (n,), "option_pick": (n,), "action": (n,)}
        self.update_noise = {"sample": (cfg.batch_size,)}

    # -- pieces ------------------------------------------------------------------------------------
    def joint(self, options: jax.Array) -> jax.Array:
        """int[..., N] options -> the critic's joint index (w1 * K + w2 for two agents)."""
        index = options[..., 0]
        for i in range(1, self.n_agents):
            index = index * self.n_options + options[..., i]
        return index.astype(jnp.int32)

    def split(self, w: jax.Array) -> jax.Array:
        """The critic's joint index -> int[..., N] options."""
        return jnp.asarray(self.coords)[w]

    def joint_obs(self, obs: jax.Array) -> jax.Array:
        """The critic's input (what replay rows store) of an env observation: the observation itself, or
        its N rows [..., N, D] side by side, [..., N * D]."""
        return obs.reshape(*obs.shape[:-2], -1) if self.per_agent else obs

    def _actors_apply(self, actor_params, obs: jax.Array, **kw):
        """Every agent's actor on obs [..., D'] (``joint_obs``): the whole of it, or agent i on its own row."""
        obs = obs.astype(jnp.float32)
        if not self.per_agent:
            return jax.vmap(lambda p: self.actor_net.apply(p, obs, **kw))(actor_params)
        rows = jnp.moveaxis(obs.reshape(*obs.shape[:-1], self.n_agents, self.obs_dim), -2, 0)  # [N, ..., D]
        return jax.vmap(lambda p, x: self.actor_net.apply(p, x, **kw))(actor_params, rows)

    def actor_out(self, actor_params, obs: jax.Array):
        """(policy logits [N, ..., K, A], termination probabilities [N, ..., K]) for obs [..., D'] (``joint_obs``)."""
        logits, beta_logits = self._actors_apply(actor_params, obs)
        return logits, jax.nn.sigmoid(beta_logits)

    def terminations(self, actor_params, obs: jax.Array) -> jax.Array:
        """beta_i(s, .) as float[N, ..., K] for obs [..., D'] (``joint_obs``)."""
        return jax.nn.sigmoid(self._actors_apply(actor_params, obs, method=OptionActor.terminations))

    def q_joint(self, critic_params, obs: jax.Array) -> jax.Array:
        """Q(s, w1, ..., wN) as float[..., K, ..., K] for obs [..., D'] (``joint_obs``)."""
        q = self.critic.q_values(critic_params, obs)
        return q.reshape(*q.shape[:-1], *(self.n_options,) * self.n_agents)

    def choose_options(self, q: jax.Array, w: jax.Array, terminate: jax.Array, eps, u_explore: jax.Array,
                       u_pick: jax.Array) -> jax.Array:
        """New options int32[N] after terminations bool[N] (module docstring: the rule U assumes): the
        agents whose options end re-choose jointly, the argmax of Q with the others' options held, or,
        exploring (decided by the first of them), uniformly at random.

        q float[K, ..., K] Q(s, .); w int32[N] options in force (>= 0); u_explore, u_pick float[N].
        """
        k = self.n_options
        rand = jnp.minimum(jnp.floor(u_pick * k), k - 1).astype(jnp.int32)
        coords = jnp.asarray(self.coords)
        held = jnp.all((coords == w) | terminate, axis=-1)  # joint options that keep the others' options
        greedy = coords[jnp.argmax(jnp.where(held, q.ravel(), -jnp.inf))]
        explore = u_explore[jnp.argmax(terminate)] < eps
        return jnp.where(terminate, jnp.where(explore, rand, greedy), w).astype(jnp.int32)

    def critic_target(self, actor_params):
        """The critic's ``target_fn`` for ``DQN.update``: U with the terminations of ``actor_params``."""

        def target(batch, q_t_target, q_t_online):
            w = self.split(batch["action"])
            beta = self.terminations(actor_params, batch["next_obs"])         # [N, B, K]
            return self._target(batch, w, beta, q_t_target, q_t_online)

        return target

    def _target(self, batch, w, beta_t, q_t_target, q_t_online):
        b = jnp.arange(w.shape[0])
        beta_t_w = jnp.stack([beta_t[i, b, w[:, i]] for i in range(self.n_agents)], axis=-1)   # [B, N]
        discount_t = self.cfg.gamma * (1.0 - batch["terminal"].astype(jnp.float32))
        shape = (-1,) + (self.n_options,) * self.n_agents
        q_t = q_t_target.reshape(shape)
        sel = q_t_online.reshape(shape) if self.cfg.double_dqn else None
        return option_critic_target(batch["reward"], discount_t, q_t, jax.lax.stop_gradient(beta_t_w), w, sel)

    def actor_loss(self, actor_params, critic: DQNState, batch: dict) -> jax.Array:
        """Every agent's intra-option policy and termination losses on ``batch`` (replay rows)."""
        doc, b = self.doc, jnp.arange(batch["action"].shape[0])
        w = self.split(batch["action"])
        a = batch["primitive"]
        n = b.shape[0]
        both = jnp.concatenate([batch["obs"], batch["next_obs"]])            # one pass over s and s'
        logits, beta_both = self.actor_out(actor_params, both)                 # [N, 2B, K, A], [N, 2B, K]
        logits_tm1, beta_tm1, beta_t = logits[:, :n], beta_both[:, :n], beta_both[:, n:]
        q_both = self.critic.q_values(critic.params, both)
        q_tm1 = q_both[:n].reshape((n,) + (self.n_options,) * self.n_agents)
        q_t_online = q_both[n:]
        q_t_target = self.critic.q_values(critic.target_params, batch["next_obs"])
        y = self._target(batch, w, beta_t, q_t_target, q_t_online)
        advantage = jax.lax.stop_gradient(y - _others_fixed(q_tm1, w, ())[:, 0])
        if doc.termination_at == "next":
            term_adv = termination_advantage(q_t_online.reshape(q_tm1.shape), w, doc.value_baseline)
            beta, mask = beta_t, 1.0 - batch["terminal"].astype(jnp.float32)
        else:
            term_adv = termination_advantage(q_tm1, w, doc.value_baseline)
            beta, mask = beta_tm1, jnp.ones(b.shape, jnp.float32)
        term_adv = jax.lax.stop_gradient(term_adv)
        loss = 0.0
        for i in range(self.n_agents):
            loss += intra_option_pg_loss(logits_tm1[i, b, w[:, i]], a[:, i], advantage, doc.entropy_weight)
            loss += termination_loss(beta[i, b, w[:, i]], term_adv[:, i], doc.xi, mask)
        return loss

    def actor_batch(self, replay: rb.Replay, u_sample: jax.Array) -> dict:
        """The rows the actor steps on (``doc.actor_data``)."""
        if self.doc.actor_data == "replay":
            return self.critic.expand(rb.sample(replay, u_sample))  # the rows DQN.update draws from the same uniforms
        idx = (replay.pos - 1 - jnp.arange(self.cfg.train_every)) % replay.capacity
        return self.critic.expand(jax.tree.map(lambda store: store[idx], replay.rows))

    def _row(self, transition: dict) -> dict:
        options = jnp.maximum(transition["next_carry"], 0)  # the options used for this step
        return {"obs": self.joint_obs(transition["obs"]), "action": self.joint(options),
                "primitive": transition["action"], "reward": transition["reward"],
                "next_obs": self.joint_obs(transition["next_obs"]),
                "terminal": transition["info"]["terminated"], "done": transition["done"]}

    # -- learner protocol ---------------------------------------------------------------------------
    def init(self, key, transition: dict) -> DOCState:
        k_critic, k_actor = jax.random.split(key)
        critic = self.critic.init(k_critic, self._row(transition))
        actor = self.init_actor(k_actor)
        return DOCState(critic=critic, actor=actor, actor_opt=self.actor_optimizer.init(actor))

    def init_actor(self, key) -> object:
        """Every agent's actor params from one uniform draw: LeCun-uniform kernels (variance 1 / fan_in,
        as flax's default), zero biases. One draw instead of one per layer and agent: under the
        trainer's vmap, per-layer random inits cost seconds of XLA compile for nothing."""
        shapes = jax.eval_shape(self.actor_net.init, jax.random.PRNGKey(0), jnp.zeros((self.obs_dim,), jnp.float32))
        leaves, treedef = jax.tree.flatten(shapes)
        sizes = [math.prod(leaf.shape) for leaf in leaves]
        u = jax.random.uniform(key, (self.n_agents, sum(sizes)), jnp.float32, -1.0, 1.0)
        params, offset = [], 0
        for leaf, size in zip(leaves, sizes):
            x = u[:, offset:offset + size].reshape(self.n_agents, *leaf.shape)
            offset += size
            params.append(x * math.sqrt(3.0 / leaf.shape[0]) if len(leaf.shape) == 2 else jnp.zeros_like(x))
        return jax.tree.unflatten(treedef, params)

    def init_carry(self) -> jax.Array:
        return jnp.full((self.n_agents,), NO_OPTION, jnp.int32)

    def act(self, state: DOCState, obs, carry, noise, step):
        eps = linear_epsilon(self.cfg, step)
        obs = self.joint_obs(obs)
        q = self.q_joint(state.critic.params, obs)
        logits, beta = self.actor_out(state.actor, obs)                        # [N, K, A], [N, K]
        w = jnp.maximum(carry, 0)
        agents = jnp.arange(self.n_agents)
        terminate = (carry == NO_OPTION) | (noise["terminate"] < beta[agents, w])
        options = self.choose_options(q, w, terminate, eps, noise["option_explore"], noise["option_pick"])
        actions = sample_categorical(jax.nn.softmax(logits[agents, options]), noise["action"])
        return actions, options

    def observe(self, state: DOCState, transition: dict) -> DOCState:
        return state.replace(critic=self.critic.add(state.critic, self._row(transition)))

    def update(self, state: DOCState, noise) -> DOCState:
        u = noise["sample"]
        batch = self.actor_batch(state.critic.replay, u)
        grads = jax.grad(self.actor_loss)(state.actor, state.critic, batch)
        updates, actor_opt = self.actor_optimizer.update(grads, state.actor_opt, state.actor)
        critic = self.critic.update(state.critic, u, self.critic_target(state.actor))
        return DOCState(critic=critic, actor=optax.apply_updates(state.actor, updates), actor_opt=actor_opt)

    def policy(self, state: DOCState):
        return {"critic": state.critic.params, "actor": state.actor}

    def greedy_act(self, params, obs, carry):
        obs = self.joint_obs(obs)
        q = self.q_joint(params["critic"], obs)
        logits, beta = self.actor_out(params["actor"], obs)
        w = jnp.maximum(carry, 0)
        agents = jnp.arange(self.n_agents)
        terminate = (carry == NO_OPTION) | (beta[agents, w] >= self.doc.greedy_termination)
        zeros = jnp.zeros((self.n_agents,))
        options = self.choose_options(q, w, terminate, 0.0, zeros, zeros)
        return jnp.argmax(logits[agents, options], axis=-1).astype(jnp.int32), options


def make_learner(env: USAREnv, cfg: DQNConfig, doc_cfg: DOCConfig | None = None,
                 options: int | None = None) -> OptionCritic:
    """DOC with ``options`` options per agent (default: the first of ``doc_cfg.options``).

    ``make_learner(env, cfg.dqn)`` (what ``experiments.train.build`` calls) gives the DOCConfig
    defaults with K = 2.
    """
    doc_cfg = doc_cfg or DOCConfig()
    return OptionCritic(env.obs_shape, N_ACTIONS, options or doc_cfg.options[0], cfg, doc_cfg, env.obs_blocks,
                        env.n_agents)
