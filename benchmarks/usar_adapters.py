"""The navigation sub-task of the peer benchmark against Stable-Baselines3, as a Gymnasium env (never
imported by the package). The multi-agent task's JaxMARL env is the package's adapter,
``jaxusar.interop.JaxMARLEnv`` (used by ``vs_jaxmarl.py`` and ``jaxmarl_iql.py``).

* ``navigation_subtask(env)``: the sub-task of the peer benchmark against Stable-Baselines3: agent 1
  (the bottom medic, start (9, 0) facing NORTH) NAVIGATE-TO-TOP-ROOM on the pseudo-reward of
  ``jaxusar.algos.subpolicies`` (+100 on entering the top room, -1 every step, terminal there, time
  limit = the horizon), trained and tested from the medic's start only (the package's
  hierarchical run trains half of its episodes from the option's whole initiation set; a fixed
  start is what a Gymnasium user would write, so both sides here use it).
* ``SubtaskGymEnv``: that sub-task as a ``gymnasium.Env`` (``terminated`` on reaching the room,
  ``truncated`` at the horizon). Its dynamics are a numpy transcription of
  ``jaxusar.envs.usar.apply_actions`` for one agent on the task's map arrays (``backend="numpy"``,
  the fast path a Gymnasium user would write), or the package's jitted ``SubtaskEnv.step`` called
  once per step (``backend="jax"``). ``check_gym_matches_jax`` rolls both against the package's env.
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np

from jaxusar import envs
from jaxusar.algos import subpolicies as sp
from jaxusar.algos.options import options_from_graph
from jaxusar.envs.usar import DIR_DELTA, FORWARD, N_ACTIONS, TURN_LEFT, TURN_RIGHT

SUBTASK = "agent1:NAVIGATE-TO-TOP-ROOM"


@dataclasses.dataclass(frozen=True)
class Subtask:
    env: object            # the USAREnv it is cut from
    senv: sp.SubtaskEnv    # the package's pseudo-reward env
    params: sp.TaskParams  # numpy, no leading task axis
    start: tuple[int, int, int]  # (row, col, dir)
    optimal_steps: int     # shortest path from the start to the sub-goal region


def navigation_subtask(horizon: int = 300, name: str = SUBTASK, gamma: float = 0.99) -> Subtask:
    """The package's task ``name``, restricted to its agent's start (training and tests); ``gamma``
    is the task's discount (the package's sub-policy learner reads it from the task, per replay row)."""
    env = envs.make("two_rooms", horizon=horizon)
    options = options_from_graph(env.graph)
    task = next(t for t in sp.make_tasks(env, options) if t.name == name)
    # the medic's start only, in training, tests and the trainer's per-state check (its initiation set)
    task = dataclasses.replace(task, starts=task.test_starts, initiation=task.test_starts)
    stacked = sp.task_params(env, [task], gamma, {})
    params = jax.tree.map(lambda x: np.asarray(x[0]), stacked)
    start = tuple(int(v) for v in task.test_starts[0, :3])  # (row, col, dir); goal index 0
    return Subtask(env, sp.SubtaskEnv(env, horizon), params, start, int(params.dist[0][start]))


class SubtaskGymEnv(gym.Env):
    """``gymnasium.Env`` of the sub-task (see the module docstring). Observation float32[obs_dim]:
    one-hot row, col, dir, then a 0 flag (the package's ``SubtaskEnv.observe``)."""

    metadata = {"render_modes": []}

    def __init__(self, task: Subtask | None = None, backend: str = "numpy"):
        self.task = task or navigation_subtask()
        p, senv = self.task.params, self.task.senv
        self.height, self.width, self.horizon = senv.height, senv.width, senv.horizon
        self.obs_dim = senv.obs_dim
        self.observation_space = gym.spaces.Box(0.0, 1.0, (self.obs_dim,), np.float32)
        self.action_space = gym.spaces.Discrete(N_ACTIONS)
        self.solid = np.asarray(p.solid, bool)
        self.in_goal = np.asarray(senv.region) == int(p.goal_region[0])
        self.backend = backend
        if backend == "jax":
            jp = jax.tree.map(jnp.asarray, p)
            self._jax_step = jax.jit(lambda s, a: senv.step(None, s, a, jp))
            self._jax_start = jax.jit(lambda: senv.reset_test(jax.random.PRNGKey(0), jp))
        elif backend != "numpy":
            raise ValueError(f"backend must be 'numpy' or 'jax', got {backend!r}")

    def _obs(self) -> np.ndarray:
        obs = np.zeros(self.obs_dim, np.float32)
        obs[self.r] = obs[self.height + self.c] = obs[self.height + self.width + self.d] = 1.0
        return obs

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.r, self.c, self.d = self.task.start
        self.t = 0
        if self.backend == "jax":
            obs, self._state = self._jax_start()
            return np.asarray(obs), {}
        return self._obs(), {}

    def step(self, action):
        action = int(action)
        if self.backend == "jax":
            obs, self._state, reward, done, info = self._jax_step(self._state, jnp.asarray([action], jnp.int32))
            obs, reward, done, terminated = jax.device_get((obs, reward, done, info["terminated"]))
            return obs, float(reward), bool(terminated), bool(done) and not bool(terminated), {}
        if action == FORWARD:
            r, c = self.r + int(DIR_DELTA[self.d, 0]), self.c + int(DIR_DELTA[self.d, 1])
            if 0 <= r < self.height and 0 <= c < self.width and not self.solid[r, c]:
                self.r, self.c = r, c
        elif action == TURN_LEFT:
            self.d = (self.d + 3) % 4
        elif action == TURN_RIGHT:
            self.d = (self.d + 1) % 4
        # TRIAGE: no victim in a navigation task, a no-op
        self.t += 1
        terminated = bool(self.in_goal[self.r, self.c])
        reward = (sp.SUCCESS_REWARD if terminated else 0.0) + sp.STEP_REWARD
        truncated = (not terminated) and self.t >= self.horizon
        return self._obs(), reward, terminated, truncated, {}


def check_gym_matches_jax(task: Subtask, episodes: int = 20, seed: int = 0) -> int:
    """Roll the numpy Gymnasium env and the package's jitted SubtaskEnv side by side on random
    actions (biased to FORWARD so episodes reach the room); raise on any difference. Returns steps."""
    g, j = SubtaskGymEnv(task, "numpy"), SubtaskGymEnv(task, "jax")
    rng = np.random.default_rng(seed)
    steps = reached = 0
    for _ in range(episodes):
        o1, _ = g.reset()
        o2, _ = j.reset()
        done = False
        while not done:
            assert np.array_equal(o1, o2), "observations differ"
            a = int(rng.choice(4, p=[0.55, 0.2, 0.2, 0.05]))
            o1, r1, te1, tr1, _ = g.step(a)
            o2, r2, te2, tr2, _ = j.step(a)
            assert (r1, te1, tr1) == (r2, te2, tr2), f"step {steps}: {(r1, te1, tr1)} != {(r2, te2, tr2)}"
            done = te1 or tr1
            steps += 1
        reached += te1
    assert 0 < reached < episodes, f"{reached} of {episodes} random episodes reached the room: a weak check"
    return steps

