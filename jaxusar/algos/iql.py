"""Independent Q-learning (paper Sec. V, Fig. 6; Tan 1993): one DQN per agent.

Each agent has its own Q-network over its 4 primitive actions, its own optimizer and its own replay
buffer; its reward is the shared team reward, and the other agents are part of its environment. Its
input is the full observation, or where the env gives each agent its own (``observation: view``,
``env.obs_shape`` [n_agents, obs_dim]), its own row. Nothing else is IQL-specific: the math is the
one-step Q-learning target, bootstrapping through time-limit truncations (only a true termination, all
victims triaged, stops the bootstrap; time is not in the observation, so treating the cap as terminal
would alias states).
"""

from __future__ import annotations

from jaxusar.config import DQNConfig
from jaxusar.core.learners import IndependentDQN, dqn_target
from jaxusar.envs import N_ACTIONS, USAREnv

ALGORITHM = "iql"


def make_learner(env: USAREnv, cfg: DQNConfig) -> IndependentDQN:
    return IndependentDQN(env.obs_shape, N_ACTIONS, env.n_agents, cfg, dqn_target(cfg), obs_blocks=env.obs_blocks)
