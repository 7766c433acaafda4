"""Adapters: the USAR world behind the APIs multi-agent users already have, so that an algorithm written
for JaxMARL or PettingZoo runs on jaxusar's maps (and the benchmark suite's tasks) unchanged.

* ``JaxMARLEnv(env)``: JaxMARL's ``MultiAgentEnv`` (jaxmarl 0.2): pure, jit-able and vmap-able
  ``reset(key) -> (obs, state)`` and ``step(key, state, actions) -> (obs, state, rewards, dones, infos)``
  on dicts keyed by agent name, auto-resetting as ``MultiAgentEnv.step`` does.
* ``ParallelEnv(env, seed=0)``: PettingZoo's Parallel API (pettingzoo 1.27) over numpy, one jitted env
  step per ``step`` call; it passes ``pettingzoo.test.parallel_api_test``.

Conventions shared by both. Agents are ``agent_0 .. agent_{n-1}`` in the env's index order (medics and
engineers numbered together, DESIGN.md contract part 2); ``agent_classes`` groups them by role. Actions
are ``Discrete(4)``: 0 FORWARD, 1 TURN_LEFT, 2 TURN_RIGHT, 3 the role's tool (TRIAGE or clear rubble).
Observations are float32[obs_dim] in [0, 1]: with ``observation="full"`` every agent gets the team's
shared vector (it determines the state); with ``"view"`` (``env.observe`` gives float32[n_agents,
obs_dim]) agent i gets row i. The reward is the team reward, given to every agent (as in JaxMARL's
cooperative tasks: a learner summing over agents counts it n times). All agents end together: when every
victim is triaged or dead (JaxMARL ``dones``, PettingZoo ``terminations``) or at the horizon (``dones``,
PettingZoo ``truncations``). Every action is always available.

Neither library is a dependency of jaxusar: importing this module needs neither, and each is imported
only where it is used (``pip install 'jaxusar[bench]'`` installs them; the ``test`` extra has pettingzoo).
``JaxMARLEnv`` needs jaxmarl only for its spaces, so its dict API runs (and is tested) without it; it is
not a subclass of ``MultiAgentEnv`` (JaxMARL's wrappers and learners use the API, not the class, and
importing jaxmarl takes seconds). ``ParallelEnv`` is a subclass of ``pettingzoo.ParallelEnv`` (some
PettingZoo wrappers check it), made when the first one is built.
"""

from __future__ import annotations

import functools
import importlib
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxusar import envs
from jaxusar.envs import ENGINEER, MEDIC, N_ACTIONS, USAREnv

INSTALL = "pip install 'jaxusar[bench]'"
ROLE_CLASSES = {MEDIC: "medic", ENGINEER: "engineer"}


def _require(user: str, *modules: str) -> list:
    """Import ``modules``; a missing one is an ImportError that names ``user`` and the extra to install."""
    try:
        return [importlib.import_module(m) for m in modules]
    except ImportError as e:
        names = sorted({m.split(".")[0] for m in modules})
        raise ImportError(f"{user} needs {' and '.join(names)} ({e.name or e} could not be imported): "
                          f"{INSTALL}") from e


@functools.cache
def _with_base(cls: type, base: type) -> type:
    """``cls`` deriving from ``base`` as well (a library's class, known only once it is imported)."""
    return type(cls.__name__, (cls, base), {"__module__": cls.__module__, "__qualname__": cls.__qualname__,
                                            "__doc__": cls.__doc__})


def _as_env(env: USAREnv | str) -> USAREnv:
    if isinstance(env, str):
        return envs.make(env)
    if not isinstance(env, USAREnv):
        raise TypeError(f"expected a jaxusar USAREnv (jaxusar.envs.make(...)) or a map name, got {type(env).__name__}")
    return env


def agent_names(env: USAREnv) -> list[str]:
    """``agent_0 .. agent_{n-1}``: JaxMARL's default names, in the env's agent index order."""
    return [f"agent_{i}" for i in range(env.n_agents)]


def agent_classes(env: USAREnv) -> dict[str, list[str]]:
    """Agent names grouped by role: ``{"medic": [...], "engineer": [...]}`` (roles the map has)."""
    names = agent_names(env)
    return {cls: [a for a, r in zip(names, env.roles) if r == role] for role, cls in ROLE_CLASSES.items()
            if np.any(env.roles == role)}


class JaxMARLEnv:
    """A jaxusar env as a JaxMARL ``MultiAgentEnv`` (see the module docstring).

    ``reset(key) -> (obs, state)``; ``step(key, state, actions, reset_state=None) -> (obs, state,
    rewards, dones, infos)``: ``step_env`` then, where ``dones["__all__"]``, the observation and state of
    ``reset(key_reset)`` (or of ``reset_state``) in place of the final ones, exactly as JaxMARL's
    ``MultiAgentEnv.step``; rewards, dones and infos stay the final step's. ``state`` is the env's
    ``EnvState``; ``infos`` is the env's info (``newly_triaged`` bool[n_victims], ``terminated``,
    ``truncated``). Obs dicts hold float32[obs_dim] per agent, rewards float32 scalars, dones bool
    scalars plus ``"__all__"``. ``reset``, ``step`` and ``get_avail_actions`` are jitted with the adapter
    static, like JaxMARL's; under ``jax.vmap`` they batch as any JaxMARL env does.

    ``observation_space(agent)`` / ``action_space(agent)`` (and the ``observation_spaces`` /
    ``action_spaces`` dicts) are jaxmarl ``Box(0, 1, (obs_dim,), float32)`` / ``Discrete(4)``: the only
    part that imports jaxmarl.
    """

    def __init__(self, env: USAREnv | str):
        self.env = _as_env(env)
        self.num_agents = self.env.n_agents
        self.agents = agent_names(self.env)
        self.obs_dim = self.env.obs_dim
        self.max_steps = self.env.horizon

    def __repr__(self) -> str:
        return f"JaxMARLEnv({self.env!r})"

    @property
    def name(self) -> str:
        return f"jaxusar_{self.env.layout.name}"

    @property
    def agent_classes(self) -> dict[str, list[str]]:
        return agent_classes(self.env)

    # -- spaces (jaxmarl's classes) ----------------------------------------------------------------
    @functools.cached_property
    def observation_spaces(self) -> dict:
        (spaces,) = _require("jaxusar.interop.JaxMARLEnv's spaces", "jaxmarl.environments.spaces")
        return {a: spaces.Box(0.0, 1.0, (self.obs_dim,), jnp.float32) for a in self.agents}

    @functools.cached_property
    def action_spaces(self) -> dict:
        (spaces,) = _require("jaxusar.interop.JaxMARLEnv's spaces", "jaxmarl.environments.spaces")
        return {a: spaces.Discrete(N_ACTIONS) for a in self.agents}

    def observation_space(self, agent: str):
        return self.observation_spaces[agent]

    def action_space(self, agent: str):
        return self.action_spaces[agent]

    # -- dicts <-> the env's arrays -----------------------------------------------------------------
    def _split(self, obs: jax.Array) -> dict[str, jax.Array]:
        if self.env.observation == "full":  # one shared vector: the same array for every agent
            return {a: obs for a in self.agents}
        return {a: obs[i] for i, a in enumerate(self.agents)}

    def joint_actions(self, actions: dict[str, Any]) -> jax.Array:
        """int32[n_agents] of an actions dict (one int per agent name; extra keys are ignored)."""
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise KeyError(f"actions has no entry for {missing}: expected one per agent of {self.agents}")
        return jnp.stack([jnp.asarray(actions[a]) for a in self.agents]).astype(jnp.int32)

    def get_obs(self, state) -> dict[str, jax.Array]:
        return self._split(self.env.observe(state))

    # -- the MultiAgentEnv API ---------------------------------------------------------------------
    @partial(jax.jit, static_argnums=0)
    def reset(self, key: jax.Array):
        obs, state = self.env.reset(key)
        return self._split(obs), state

    def step_env(self, key: jax.Array, state, actions: dict[str, Any]):
        """One step without auto-reset (JaxMARL's ``step_env``)."""
        obs, state, reward, done, info = self.env.step(key, state, self.joint_actions(actions))
        rewards = {a: reward for a in self.agents}
        dones = {**{a: done for a in self.agents}, "__all__": done}
        return self._split(obs), state, rewards, dones, info

    @partial(jax.jit, static_argnums=0)
    def step(self, key: jax.Array, state, actions: dict[str, Any], reset_state=None):
        # MultiAgentEnv.step of jaxmarl 0.2.0, line for line: the same key split, the reset always
        # computed and selected where the episode is done.
        key, key_reset = jax.random.split(key)
        obs_st, state_st, rewards, dones, infos = self.step_env(key, state, actions)
        if reset_state is None:
            obs_re, state_re = self.reset(key_reset)
        else:
            state_re, obs_re = reset_state, self.get_obs(reset_state)
        done = dones["__all__"]
        state = jax.tree.map(lambda x, y: jax.lax.select(done, x, y), state_re, state_st)
        obs = jax.tree.map(lambda x, y: jax.lax.select(done, x, y), obs_re, obs_st)
        return obs, state, rewards, dones, infos

    @partial(jax.jit, static_argnums=0)
    def get_avail_actions(self, state) -> dict[str, jax.Array]:
        """bool[4] per agent, all True: every action is legal (a blocked move or a tool with nothing in
        front is a no-op, as in Minigrid)."""
        del state
        return {a: jnp.ones((N_ACTIONS,), bool) for a in self.agents}


RENDER_MODES = ("ansi", "human")


def _seed(seed: int | None) -> int:
    return int(np.random.SeedSequence().entropy % 2**32) if seed is None else int(seed)


class ParallelEnv:
    """A jaxusar env as a PettingZoo ``ParallelEnv`` (see the module docstring).

    ``seed``: the PRNG seed of resets called without one (drawn victims; the env's step takes a key
    too); None draws one from the OS, as Gymnasium does. ``reset(seed=s)`` restarts the key stream
    from ``s``. Observations are numpy float32[obs_dim]
    per agent; rewards Python floats; ``terminations`` when every victim is triaged or dead,
    ``truncations`` at the horizon; ``infos[agent]`` holds the team's ``newly_triaged`` bool[n_victims].
    ``agents`` is every agent from ``reset`` until the episode ends, then empty. ``env_state`` is the
    env's current ``EnvState`` (None before ``reset``), to inspect or render. Every agent must act on
    every step. ``render_mode="ansi"`` returns the map as text from ``render()``, ``"human"`` prints it.

    The env's reset and step are jitted once per adapter (one XLA program each; the first call
    compiles), and each ``step`` moves its outputs to numpy in one transfer.
    """

    metadata: dict

    def __new__(cls, *args, **kwargs):
        # a subclass of pettingzoo's ParallelEnv, made here so that importing this module needs no pettingzoo
        (pettingzoo,) = _require("jaxusar.interop.ParallelEnv", "pettingzoo")
        base = pettingzoo.ParallelEnv
        return super().__new__(cls if issubclass(cls, base) else _with_base(cls, base))

    def __init__(self, env: USAREnv | str, seed: int | None = 0, render_mode: str | None = None):
        (spaces,) = _require("jaxusar.interop.ParallelEnv", "gymnasium.spaces")
        self.env = env = _as_env(env)
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode={render_mode!r}: expected None or one of {RENDER_MODES}")
        self.render_mode = render_mode
        self.metadata = {"name": f"jaxusar_{env.layout.name}", "render_modes": list(RENDER_MODES),
                         "is_parallelizable": True}
        self.possible_agents = agent_names(env)
        self.agents: list[str] = []
        # built once: the API requires the same space object on every call
        self.observation_spaces = {a: spaces.Box(0.0, 1.0, (env.obs_dim,), np.float32) for a in self.possible_agents}
        self.action_spaces = {a: spaces.Discrete(N_ACTIONS) for a in self.possible_agents}
        self._key = jax.random.PRNGKey(_seed(seed))
        self.env_state = None

        def reset(key):
            key, sub = jax.random.split(key)
            obs, state = env.reset(sub)
            return key, obs, state

        def step(key, state, actions):
            key, sub = jax.random.split(key)
            obs, state, reward, _, info = env.step(sub, state, actions)
            return key, state, (obs, reward, info)

        self._reset, self._step = jax.jit(reset), jax.jit(step)

    def __repr__(self) -> str:
        return f"ParallelEnv({self.env!r})"

    def observation_space(self, agent: str):
        return self.observation_spaces[agent]

    def action_space(self, agent: str):
        return self.action_spaces[agent]

    def _per_agent(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        if self.env.observation == "full":
            return {a: obs for a in self.possible_agents}
        return {a: obs[i] for i, a in enumerate(self.possible_agents)}

    def reset(self, seed: int | None = None, options: dict | None = None):
        del options  # none: a task's settings are the env's
        if seed is not None:
            self._key = jax.random.PRNGKey(_seed(seed))
        self._key, obs, self.env_state = self._reset(self._key)
        self.agents = list(self.possible_agents)
        return self._per_agent(np.asarray(obs)), {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]):
        if not self.agents:
            raise RuntimeError("no live agents: the episode has ended (or reset() was never called); call reset()")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise KeyError(f"actions has no entry for {missing}: every agent acts on every step ({self.agents})")
        joint = np.asarray([actions[a] for a in self.possible_agents])
        if not np.issubdtype(joint.dtype, np.integer) or np.any((joint < 0) | (joint >= N_ACTIONS)):
            raise ValueError(f"actions must be integers in 0..{N_ACTIONS - 1}, got {joint.tolist()}")
        self._key, self.env_state, out = self._step(self._key, self.env_state, joint.astype(np.int32))
        obs, reward, info = jax.device_get(out)
        agents = self.agents
        terminated, truncated = bool(info["terminated"]), bool(info["truncated"])
        if terminated or truncated:
            self.agents = []
        return (self._per_agent(obs), {a: float(reward) for a in agents}, {a: terminated for a in agents},
                {a: truncated for a in agents}, {a: {"newly_triaged": info["newly_triaged"]} for a in agents})

    def render(self) -> str | None:
        if self.render_mode is None:
            (gymnasium,) = _require("jaxusar.interop.ParallelEnv", "gymnasium")
            gymnasium.logger.warn("render() without a render_mode: pass render_mode='ansi' or 'human' to ParallelEnv")
            return None
        if self.env_state is None:
            raise RuntimeError("nothing to render before reset()")
        text = self.env.render_ascii(self.env_state)
        if self.render_mode == "human":
            print(text)
            return None
        return text

    def close(self) -> None:
        self.env_state, self.agents = None, []
