"""QMIX (Rashid et al. 2018): the team's Q is a monotonic mixing network of the agents' Qs,
conditioned on the state.

Q_tot = elu(q W1 + b1) W2 + V, with q = (Q_1(o_1, a_1), ..., Q_n(o_n, a_n)) and W1 [n, E], b1 [E], W2 [E], V
produced from the state by hypernetworks; W1 and W2 pass through abs, so dQ_tot/dQ_i >= 0 and each agent's
own argmax is the team's (the paper's monotonicity constraint, eq. 5). As in the paper, each weight's
hypernetwork is one linear layer and V is two (ReLU between); pymarl and JaxMARL also offer two-layer weight
hypernetworks. The state is the env's full observation, or the agents' rows concatenated where the env gives
each agent its own (``observation: view``). Agents do not share parameters (one MLP each, as IQL and VDN);
everything but the mixer (agents' networks, replay, target, update, trainer) is ``core.learners.TeamDQN``'s.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxusar.config import DQNConfig
from jaxusar.core.learners import TeamDQN
from jaxusar.envs import N_ACTIONS, USAREnv

ALGORITHM = "qmix"
DESCRIPTION = "QMIX (Rashid et al. 2018): the team's Q is a monotonic mixing network of the agents' Qs and the state."

EMBED = 8  # the mixing layer's width (the paper: 32, for up to 8 SMAC agents; 2-4 agents here, and on CPU the
# hypernetworks' first layer, state width x (n + 3) x EMBED, is most of what QMIX adds to VDN's update)


class MonotonicMixer(nn.Module):
    """Q_tot(q float[..., n], state float[..., S]) -> float[...], non-decreasing in every q_i."""

    embed: int = EMBED

    @nn.compact
    def __call__(self, q: jax.Array, state: jax.Array) -> jax.Array:
        n, e = q.shape[-1], self.embed
        # the first layers of the four hypernetworks (W1, b1, W2 and V's hidden layer) as one matmul
        first = nn.Dense(n * e + 3 * e, name="hypernetworks")(state)
        w1, b1, w2, v = jnp.split(first, [n * e, n * e + e, n * e + 2 * e], -1)
        w1 = jnp.abs(w1).reshape(*state.shape[:-1], n, e)
        v = nn.Dense(1, name="hyper_v_out")(nn.relu(v))[..., 0]
        hidden = nn.elu((q[..., None] * w1).sum(-2) + b1)  # elementwise, which XLA fuses, not a batched matmul
        return (hidden * jnp.abs(w2)).sum(-1) + v


def make_learner(env: USAREnv, cfg: DQNConfig) -> TeamDQN:
    return TeamDQN(env.obs_shape, N_ACTIONS, env.n_agents, cfg, MonotonicMixer(), obs_blocks=env.obs_blocks)
