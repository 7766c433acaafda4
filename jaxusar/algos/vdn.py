"""Value-decomposition networks (VDN; Sunehag et al. 2018): the team's Q is the sum of the agents' Qs.

Q_tot(s, a) = sum_i Q_i(o_i, a_i), fitted by one TD loss to the team reward on one team replay; each agent
acts on its own Q_i, whose argmax is the team's (a sum is monotonic in every term). Agents do not share
parameters (one MLP each, as IQL; the paper's weight sharing with an agent id is not needed for 2-4 agents and
keeps one agent's VDN exactly one DQN); agent i sees the full observation, or its own row where the env gives
one per agent (``observation: view``). Everything else (agents' networks, replay, target, update, trainer) is
``core.learners.TeamDQN``'s.
"""

from __future__ import annotations

import flax.linen as nn
import jax

from jaxusar.config import DQNConfig
from jaxusar.core.learners import TeamDQN
from jaxusar.envs import N_ACTIONS, USAREnv

ALGORITHM = "vdn"
DESCRIPTION = "Value-decomposition networks (VDN; Sunehag et al. 2018): the team's Q is the sum of the agents' Qs."


class SumMixer(nn.Module):
    """Q_tot = sum_i Q_i: no parameters, the state unused."""

    @nn.compact
    def __call__(self, q: jax.Array, state: jax.Array) -> jax.Array:
        return q.sum(-1)


def make_learner(env: USAREnv, cfg: DQNConfig) -> TeamDQN:
    return TeamDQN(env.obs_shape, N_ACTIONS, env.n_agents, cfg, SumMixer(), obs_blocks=env.obs_blocks)
