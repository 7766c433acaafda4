"""The one learning core every algorithm shares: replay, Q-learning update, scan trainer, trials."""

from jaxusar.core import checkpoint, learners, qlearning, replay, trainer
from jaxusar.core.learners import IndependentDQN, Learner, TeamDQN
from jaxusar.core.trainer import Trainer, TrainState

__all__ = ["checkpoint", "learners", "qlearning", "replay", "trainer", "IndependentDQN", "Learner", "TeamDQN", "Trainer",
           "TrainState"]
