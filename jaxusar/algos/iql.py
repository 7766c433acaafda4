"""Independent Q-learning (paper Sec. V, Fig. 6; Tan 1993): one DQN per agent.

Each medic has its own Q-network over its 4 primitive actions, its own optimizer and its own replay
buffer; its input is the full observation and its reward the shared team reward. The other medic is
part of its environment. Nothing else is IQL-specific: the math is the one-step Q-learning target,
bootstrapping through time-limit truncations (only a true termination, all victims triaged, stops
the bootstrap; time is not in the observation, so treating the cap as terminal would alias states).
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxusar.config import DQNConfig
from jaxusar.core.learners import IndependentDQN
from jaxusar.core.qlearning import double_q_learning_target, q_learning_target
from jaxusar.envs import N_ACTIONS, USAREnv


def one_step_target(cfg: DQNConfig):
    """The DQN / Double-DQN target as a function of a replay batch."""

    def target(batch, q_t_target, q_t_online):
        discount_t = cfg.gamma * (1.0 - batch["terminal"].astype(jnp.float32))
        if cfg.double_dqn:
            return double_q_learning_target(batch["reward"], discount_t, q_t_target, q_t_online)
        return q_learning_target(batch["reward"], discount_t, q_t_target)

    return target


def make_learner(env: USAREnv, cfg: DQNConfig) -> IndependentDQN:
    return IndependentDQN(env.obs_dim, N_ACTIONS, env.n_agents, cfg, one_step_target(cfg))
