"""The scan trainer: N trials of one learner on one env, as jitted chunks of a single ``lax.scan``.

Shape of a chunk (one jitted call, all trials at once)::

    scan over iterations:                      # one iteration = train_every env steps + one update
        scan over train_every steps:
            vmap over trials: act, env.step, observe, episode bookkeeping, auto-reset
        if any trial finished a test-due episode: snapshot its policy params   (lax.cond)
        if some trial's snapshot slots are full, or at the chunk's last
          iteration any are used: evaluate them                                 (lax.cond)
        if step >= learning_starts: vmap over trials: learner.update           (lax.cond)

    evaluate = for each snapshot slot some trial used: vmap over trials: greedy test episode
        (a while loop: stops when every lane is done); record it, keep the best params

The conditions of every ``lax.cond`` are scalars equal across trials, so vmap never turns them into
selects that run both branches (DESIGN.md). Greedy tests are evaluated from parameter snapshots in
batched calls, when ``n_slots`` snapshots have piled up and at the chunk's end (a per-trial test
inside the step would run on every step); the few slots bound the snapshots' memory at any chunk size.
All randomness of a chunk comes from ``fold_in(trial_key, chunk_index)``, so a trial's numbers do not
depend on which other trials run beside it: the acting noise is drawn up front, the update noise (a
batch of uniforms per update) one iteration at a time (``uniform_row``: the same numbers, without
holding them all).

An env may take per-trial parameters (gymnax style: ``reset(key, params)``, ``step(key, state,
action, params)``): the sub-policy tasks of the paper's method are one batch of such trials. An env
may also say where its tests start (``reset_test``) and what is optimal from there
(``optimal_steps_from``); otherwise tests start like training and ``optimal_steps`` is fixed. An env
with initiation states (``coverage(greedy, params)``: the fraction of them from which the greedy policy
is optimal, and which) is judged by that instead: a test is optimal at 1.0, and the kept params are the
most covering ones; the test episode's own optimality is still recorded (``test_start_optimal``). Such an
env may also take each test's verdict per state back into its params (``refocus(params, good)``), to
start later training episodes where the policy still fails.

Trials run until every trial has ``episodes`` training episodes; a trial that is done early keeps
stepping within its chunk (a vmap cannot stop one lane) but records nothing more, so its results are
exactly those of running it alone. Between chunks the host drops finished trials: once the ones still
running fit a smaller bucket than the whole batch (a power of two, or three quarters of one:
``batch_bucket``), the next chunks run those only, gathered into a batch padded to that bucket and
scattered back (``lanes_to_run``), so a slow trial no longer makes every finished one pay (each smaller
batch compiles its chunk once, counted in the run's seconds; ``train.drop_finished=false`` keeps the
whole batch, where runs are too short for that compile to pay).

Episode ``i``'s return and length, test ``j`` (after training episode ``(j + 1) * test_every``), the
best test's params (paper Sec. V: catastrophic forgetting) and ``episodes_to_optimal`` (the
training-episode count at the first optimal test) are kept per trial.
"""

from __future__ import annotations

import math
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.extend.random import threefry2x32_p

from jaxusar.config import ConfigError, TrainConfig

NO_TEST = -1
NEVER = np.iinfo(np.int32).max
MAX_SNAPSHOT_SLOTS = 8  # policy snapshots awaiting their greedy test, per trial


def trial_devices(devices=None) -> list:
    """The devices a trials axis is sharded over: ``devices``, or by default every local device."""
    return list(jax.local_devices() if devices is None else devices)


@struct.dataclass
class Snapshots:
    params: object        # [S, ...] policy params
    test_index: jax.Array  # int32[S], NO_TEST where unused
    count: jax.Array       # slots used in this chunk


@struct.dataclass
class TrialState:
    """Everything one trial carries between steps (the trainer adds a leading trials axis)."""

    key: jax.Array
    env_params: object        # per-trial env parameters (None for an env without any)
    env_state: object
    obs: jax.Array
    actor: object
    learner: object
    episodes: jax.Array       # training episodes finished
    ep_return: jax.Array
    ep_length: jax.Array
    env_steps: jax.Array      # primitive actions of all agents in training episodes until the budget was reached
    pending_test: jax.Array   # test index due at the end of this iteration, or NO_TEST
    snaps: Snapshots
    train_return: jax.Array   # float32[episodes + 1]; the last slot is a write-off
    train_length: jax.Array   # int32[episodes + 1]
    test_return: jax.Array    # float32[n_tests + 1]
    test_length: jax.Array    # int32[n_tests + 1]
    test_optimal: jax.Array   # bool[n_tests + 1]
    test_solved: jax.Array    # bool[n_tests + 1]: the test terminated (task solved), at any length
    test_start_optimal: jax.Array  # bool[n_tests + 1]: the test episode itself was optimal (from its start)
    test_coverage: jax.Array  # float32[n_tests + 1]: fraction of initiation states optimal (env.coverage; else nan)
    best_params: object
    best_coverage: jax.Array
    best_return: jax.Array
    best_length: jax.Array
    best_test: jax.Array
    first_optimal_test: jax.Array


@struct.dataclass
class TrainState:
    trials: TrialState        # leading trials axis
    step: jax.Array           # env steps per trial so far (equal across trials)
    chunk: jax.Array          # chunks run so far


def uniform_row(key: jax.Array, shape: tuple, row) -> jax.Array:
    """Row ``row`` of ``jax.random.uniform(key, (n, *shape))`` (any n), without drawing the other rows.

    JAX's threefry bits (``jax_threefry_partitionable``, the default) hash each element's flat index, and
    uniform keeps a float's mantissa bits: both are reproduced here for the indices of one row, bit for bit
    (tests/test_core.py compares them with ``jax.random.uniform``, so a JAX that draws otherwise fails there).
    The whole array must hold fewer than 2^32 numbers."""
    size = math.prod(shape)
    lo = jnp.asarray(row, jnp.uint32) * jnp.uint32(size) + jnp.arange(size, dtype=jnp.uint32)
    data = jax.random.key_data(key) if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else key
    b1, b2 = threefry2x32_p.bind(data[0], data[1], jnp.zeros_like(lo), lo)
    mantissa = ((b1 ^ b2) >> jnp.uint32(9)) | jnp.uint32(0x3F800000)  # float32: 23 mantissa bits, exponent of 1.0
    return (jax.lax.bitcast_convert_type(mantissa, jnp.float32) - 1.0).reshape(shape)


def _steps_of(info) -> jax.Array:
    """Primitive steps an env step took (an SMDP env reports ``steps``; a plain env takes 1)."""
    return info.get("steps", jnp.ones((), jnp.int32)) if isinstance(info, dict) else jnp.ones((), jnp.int32)


def batch_bucket(live: int) -> int:
    """The batch that ``live`` running trials are padded to once compacted: the next power of two, or from
    24 on three quarters of one where that fits (24, 48, 96, 192, ...: at most a third is padding, not
    half). Few sizes, so few programs compile. Below 24 only powers of two, as before: a batch of fewer
    than 16 lanes, where XLA CPU rounds the update differently from a wider one, runs at the size it
    always did (benchmarks/README.md, "Finished trials stop costing")."""
    size = 1 << math.ceil(math.log2(max(live, 1)))
    return size * 3 // 4 if size >= 32 and live <= size * 3 // 4 else size


def seconds_to_go(elapsed: float, start: float, now: float) -> float | None:
    """Seconds left at the pace so far, ``elapsed`` seconds having moved the slowest trial from fraction
    ``start`` to ``now`` of its episodes; None before it has moved (no pace to go by)."""
    return elapsed * (1 - now) / (now - start) if now > start else None


class Trainer:
    """Trains ``learner`` on ``env`` for ``cfg.episodes`` episodes per trial.

    Args:
      env: reset(key) -> (obs, state); step(key, state, action) -> (obs, state, reward, done, info),
        info["terminated"] true only when the task is solved (not at the time limit); ``horizon``.
      learner: see ``jaxusar.core.learners``.
      cfg: TrainConfig. learning_starts, train_every, gradient_steps: from the learner's DQNConfig (every
        ``train_every`` env steps, ``gradient_steps`` calls of ``learner.update``: a replay ratio of
        gradient_steps / train_every updates per env step).
      optimal_steps: a test episode is optimal when it terminates within optimal_steps + slack steps.
      min_episode_steps: fewest env steps any episode can take (checks that no two tests fall between
        updates); defaults to min(optimal_steps, horizon).
    """

    def __init__(self, env, learner, cfg: TrainConfig, *, learning_starts: int, train_every: int,
                 optimal_steps: int, min_episode_steps: int | None = None, test_horizon: int | None = None,
                 gradient_steps: int = 1):
        self.env, self.learner, self.cfg = env, learner, cfg
        self.drop_finished = cfg.drop_finished  # lanes_to_run
        self.learning_starts, self.train_every = learning_starts, train_every
        self.gradient_steps = int(gradient_steps)
        self.optimal_steps = int(optimal_steps)
        self.test_horizon = int(test_horizon or env.horizon)
        self.min_episode_steps = int(min_episode_steps or max(1, min(optimal_steps, env.horizon)))
        if cfg.test_every * self.min_episode_steps < train_every:
            raise ConfigError(
                f"train.test_every={cfg.test_every} episodes can take as few as "
                f"{cfg.test_every * self.min_episode_steps} env steps, fewer than dqn.train_every={train_every}: "
                "two tests could fall between updates; raise test_every or lower train_every")
        self.iters = max(1, cfg.chunk_steps // train_every)
        self.chunk_steps = self.iters * train_every
        self.n_tests = cfg.episodes // cfg.test_every
        self.n_slots = min(self.iters, MAX_SNAPSHOT_SLOTS)
        if any(self.iters * self.gradient_steps * math.prod(shape) >= 2 ** 32 for shape in learner.update_noise.values()):
            raise ConfigError(f"a chunk of {self.chunk_steps} steps draws 2^32 or more update numbers per trial; "
                              "lower train.chunk_steps")
        # env steps are counted as primitive actions of all agents: an env of ``n_agents`` (default 1) whose
        # info["steps"] (default 1) says how many primitive steps a call took (the coordinator's decisions)
        self.agents = int(getattr(env, "n_agents", 1))
        self.has_coverage = hasattr(env, "coverage")
        self.refocuses = self.has_coverage and hasattr(env, "refocus")  # takes each test's per-state verdict
        self._chunk = jax.jit(self._run_chunk, donate_argnums=0)
        self._lanes_chunk = jax.jit(self._run_lanes, donate_argnums=0)
        self._init = jax.jit(jax.vmap(self._init_trial))

    # -- state ----------------------------------------------------------------------------------
    def init(self, keys: jax.Array, env_params=None) -> TrainState:
        """Fresh state for ``len(keys)`` trials; ``env_params`` (leading trials axis) for a
        parameterised env (``reset(key, params)``, ``step(key, state, action, params)``)."""
        return TrainState(trials=self._init(keys, env_params), step=jnp.zeros((), jnp.int32),
                          chunk=jnp.zeros((), jnp.int32))

    # -- env calls, with or without per-trial params --------------------------------------------
    def _reset(self, key, env_params):
        return self.env.reset(key) if env_params is None else self.env.reset(key, env_params)

    def _step(self, state, action, env_params):
        if env_params is None:
            return self.env.step(None, state, action)
        return self.env.step(None, state, action, env_params)

    def _optimal_steps(self, env_state, env_params):
        """The optimum a test from ``env_state`` is held to: the env's own per-start answer if it
        has one (random-start tasks), else the fixed ``optimal_steps``."""
        if hasattr(self.env, "optimal_steps_from"):
            return self.env.optimal_steps_from(env_state, env_params)
        return jnp.asarray(self.optimal_steps, jnp.int32)

    def _init_trial(self, key, env_params) -> TrialState:
        k_env, k_learner = jax.random.split(jax.random.fold_in(key, 0x5EED))
        obs, env_state = self._reset(k_env, env_params)
        actor = self.learner.init_carry()
        action = jnp.zeros(self.learner.action_shape, jnp.int32)
        # the learner's init reads only the transition's shapes: zeros shaped like a step keep the env's step
        # out of this program (it compiles once per trainer; the step made it seconds longer on big maps)
        step = jax.eval_shape(self._step, env_state, action, env_params)
        next_obs, _, reward, done, info = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), step)
        transition = {"obs": obs, "action": action, "reward": reward, "next_obs": next_obs, "done": done,
                      "info": info, "carry": actor, "next_carry": actor}
        learner = self.learner.init(k_learner, transition)
        params = self.learner.policy(learner)
        n, t = self.cfg.episodes, self.n_tests
        zeros_like_slots = jax.tree.map(lambda p: jnp.zeros((self.n_slots, *p.shape), p.dtype), params)
        return TrialState(
            key=key, env_params=env_params, env_state=env_state, obs=obs, actor=actor, learner=learner,
            episodes=jnp.zeros((), jnp.int32), ep_return=jnp.zeros((), jnp.float32),
            ep_length=jnp.zeros((), jnp.int32), env_steps=jnp.zeros((), jnp.int32),
            pending_test=jnp.full((), NO_TEST, jnp.int32),
            snaps=Snapshots(zeros_like_slots, jnp.full((self.n_slots,), NO_TEST, jnp.int32), jnp.zeros((), jnp.int32)),
            train_return=jnp.zeros((n + 1,), jnp.float32), train_length=jnp.zeros((n + 1,), jnp.int32),
            test_return=jnp.zeros((t + 1,), jnp.float32), test_length=jnp.zeros((t + 1,), jnp.int32),
            test_optimal=jnp.zeros((t + 1,), bool), test_solved=jnp.zeros((t + 1,), bool),
            test_start_optimal=jnp.zeros((t + 1,), bool), test_coverage=jnp.full((t + 1,), jnp.nan, jnp.float32),
            best_params=params, best_coverage=jnp.full((), -jnp.inf, jnp.float32),
            best_return=jnp.full((), -jnp.inf, jnp.float32),
            best_length=jnp.full((), NEVER, jnp.int32), best_test=jnp.full((), NO_TEST, jnp.int32),
            first_optimal_test=jnp.full((), NEVER, jnp.int32),
        )

    # -- one chunk ------------------------------------------------------------------------------
    def _noise(self, trials: TrialState, chunk):
        """This chunk's acting uniforms, shaped [iters, train_every, trials, ...], and its update keys, one per
        name of ``learner.update_noise`` (uint32[trials, names, 2]): ``_update_noise`` draws an iteration's
        update uniforms from them (the update noise, batch-sized per lane-step, is most of a chunk's noise)."""

        def per_trial(key):
            key = jax.random.fold_in(key, chunk)
            k_act, k_upd, k_reset = jax.random.split(key, 3)
            act = {name: jax.random.uniform(jax.random.fold_in(k_act, i), (self.iters, self.train_every, *shape))
                   for i, (name, shape) in enumerate(sorted(self.learner.act_noise.items()))}
            act["reset_key"] = jax.random.split(k_reset, (self.iters, self.train_every))
            names = range(len(self.learner.update_noise))  # no names: one unused key keeps the shapes
            upd = jnp.stack([jax.random.fold_in(k_upd, i) for i in names] or [k_upd])
            return act, upd

        act, upd_keys = jax.vmap(per_trial)(trials.key)
        return jax.tree.map(lambda x: jnp.moveaxis(x, 0, 2), act), upd_keys

    def _update_noise(self, upd_keys, iteration):
        """Iteration ``iteration``'s update uniforms, [gradient_steps, trials, ...]: row ``iteration`` of
        ``uniform(key, (iters, gradient_steps, *shape))`` per trial and name, computed alone (``uniform_row``),
        so a chunk never holds all its iterations' noise (0.75 GiB for 192 sub-policy lanes)."""
        def per_trial(keys):
            return {name: uniform_row(keys[i], (self.gradient_steps, *shape), iteration)
                    for i, (name, shape) in enumerate(sorted(self.learner.update_noise.items()))}

        return jax.tree.map(lambda x: jnp.moveaxis(x, 0, 1), jax.vmap(per_trial)(upd_keys))

    def _env_step(self, s: TrialState, noise, step) -> TrialState:
        lrn, cfg = self.learner, self.cfg
        action, actor = lrn.act(s.learner, s.obs, s.actor, noise, step)
        next_obs, env_state, reward, done, info = self._step(s.env_state, action, s.env_params)
        learner = lrn.observe(s.learner, {"obs": s.obs, "action": action, "reward": reward, "next_obs": next_obs,
                                          "done": done, "info": info, "carry": s.actor, "next_carry": actor})
        ep_return, ep_length = s.ep_return + reward, s.ep_length + _steps_of(info)
        live = self._live(s.episodes, s.first_optimal_test)
        counted = done & live
        slot = jnp.where(counted, s.episodes, cfg.episodes)
        episodes = s.episodes + counted
        test_due = counted & (episodes % cfg.test_every == 0)
        obs0, state0 = self._reset(noise["reset_key"], s.env_params)
        pick = lambda a, b: jax.tree.map(lambda x, y: jnp.where(done, x, y), a, b)
        return s.replace(
            env_state=pick(state0, env_state), obs=pick(obs0, next_obs), actor=pick(lrn.init_carry(), actor),
            learner=learner, episodes=episodes,
            ep_return=jnp.where(done, 0.0, ep_return), ep_length=jnp.where(done, 0, ep_length),
            env_steps=s.env_steps + live * _steps_of(info) * self.agents,
            pending_test=jnp.where(test_due, episodes // cfg.test_every - 1, s.pending_test),
            train_return=s.train_return.at[slot].set(ep_return),
            train_length=s.train_length.at[slot].set(ep_length),
        )

    def _live(self, episodes, first_optimal_test):
        """Whether trials still train: short of their episodes, and with ``stop_at_optimal`` not yet
        tested optimal (jax or numpy arrays). A trial that is not records nothing more."""
        live = episodes < self.cfg.episodes
        return live & (first_optimal_test == NEVER) if self.cfg.stop_at_optimal else live

    def _counts(self, state: TrainState):
        return (np.asarray(state.trials.episodes), np.asarray(state.trials.first_optimal_test))

    def _snapshot(self, s: TrialState) -> TrialState:
        due = s.pending_test != NO_TEST
        slot = jnp.minimum(s.snaps.count, self.n_slots - 1)
        params = jax.tree.map(lambda store, p: store.at[slot].set(jnp.where(due, p, store[slot])),
                              s.snaps.params, self.learner.policy(s.learner))
        index = s.snaps.test_index.at[slot].set(jnp.where(due, s.pending_test, s.snaps.test_index[slot]))
        return s.replace(snaps=Snapshots(params, index, s.snaps.count + due),
                         pending_test=jnp.full((), NO_TEST, jnp.int32))

    def greedy_episode(self, params, key, env_params=None):
        """One greedy test episode: (return, primitive steps, terminated, optimal steps from its start).

        A while loop, so a test that ends early costs only its own steps (under vmap: the longest lane's).
        """
        return self.greedy_rollout(params, key, env_params)[:4]

    def greedy_rollout(self, params, key, env_params=None):
        """``greedy_episode``'s four values and the env state the episode ended in (what it saved)."""
        if hasattr(self.env, "reset_test"):  # an env whose tests start elsewhere than its training
            obs, env_state = self.env.reset_test(key, env_params)
        else:
            obs, env_state = self._reset(key, env_params)
        optimal = self._optimal_steps(env_state, env_params)
        zero_f, zero_i, false = jnp.zeros((), jnp.float32), jnp.zeros((), jnp.int32), jnp.zeros((), bool)

        def body(c):
            obs, es, actor, ret, length, calls, _, _ = c
            action, actor = self.learner.greedy_act(params, obs, actor)
            obs, es, r, done, info = self._step(es, action, env_params)
            return obs, es, actor, ret + r, length + _steps_of(info), calls + 1, done, info["terminated"]

        def cond(c):
            return ~c[6] & (c[5] < self.test_horizon)

        c = jax.lax.while_loop(cond, body, (obs, env_state, self.learner.init_carry(), zero_f, zero_i, zero_i,
                                            false, false))
        return c[3], c[4], c[7], optimal, c[1]

    def coverage(self, params, env_params=None):
        """``(fraction, good)``: the env's exact fraction of initiation states from which the greedy policy
        is optimal and which ones (``env.coverage``), or (nan, None) for an env without initiation states."""
        if not self.has_coverage:
            return jnp.full((), jnp.nan, jnp.float32), None
        greedy = lambda obs: self.learner.greedy_act(params, obs, self.learner.init_carry())[0]
        fraction, good = self.env.coverage(greedy, env_params)
        return fraction.astype(jnp.float32), good

    def _evaluate_slot(self, s: TrialState, j) -> TrialState:
        """Run snapshot ``j``'s greedy test (if the slot is used); record it; keep the best params.

        For an env with initiation states (``env.coverage``), a test is optimal when the policy is optimal
        from every one of them, and the best params are those optimal from the most (then the best test
        episode); else the test episode decides both."""
        test = s.snaps.test_index[j]
        params = jax.tree.map(lambda x: x[j], s.snaps.params)
        if self.cfg.test_draws == 1:
            key = jax.random.fold_in(jax.random.fold_in(s.key, 0x7E57), test)
            ret, length, terminated, optimal_steps = self.greedy_episode(params, key, s.env_params)
        else:  # the same draws at every test of the trial: the kept params are the best on them
            keys = jax.random.split(jax.random.fold_in(s.key, 0x7E57), self.cfg.test_draws)
            ret, length, terminated, optimal_steps = jax.vmap(self.greedy_episode, in_axes=(None, 0, None))(
                params, keys, s.env_params)
            ret, terminated, optimal_steps = ret.mean(), terminated.all(), optimal_steps.max()
            length = jnp.round(length.mean()).astype(length.dtype)
        cov, good = self.coverage(params, s.env_params)
        used = test != NO_TEST
        env_params = s.env_params
        if self.refocuses:  # the env starts some episodes where this test was not optimal
            env_params = jax.tree.map(lambda new, old: jnp.where(used, new, old),
                                      self.env.refocus(env_params, good), env_params)
        start_optimal = used & terminated & (length <= optimal_steps + self.cfg.optimal_slack)
        optimal = used & (cov >= 1.0) if self.has_coverage else start_optimal
        idx = jnp.where(used, test, self.n_tests)
        # best = most initiation states optimal, then highest return, then fewest steps; the earlier test
        # wins a tie (slots are in test order)
        c, best_c = (cov, s.best_coverage) if self.has_coverage else (jnp.zeros(()), jnp.zeros(()))
        better = used & ((c > best_c) | ((c == best_c) & ((ret > s.best_return) |
                                                          ((ret == s.best_return) & (length < s.best_length)))))
        return s.replace(
            env_params=env_params,
            test_return=s.test_return.at[idx].set(ret), test_length=s.test_length.at[idx].set(length),
            test_optimal=s.test_optimal.at[idx].set(optimal), test_solved=s.test_solved.at[idx].set(used & terminated),
            test_start_optimal=s.test_start_optimal.at[idx].set(start_optimal),
            test_coverage=s.test_coverage.at[idx].set(cov),
            best_params=jax.tree.map(lambda new, old: jnp.where(better, new, old), params, s.best_params),
            best_coverage=jnp.where(better, cov, s.best_coverage),
            best_return=jnp.where(better, ret, s.best_return),
            best_length=jnp.where(better, length, s.best_length),
            best_test=jnp.where(better, test, s.best_test),
            first_optimal_test=jnp.where(optimal, jnp.minimum(s.first_optimal_test, test), s.first_optimal_test),
        )

    def _evaluate(self, trials: TrialState) -> TrialState:
        """All snapshots of this chunk, slot by slot; slots no trial used are skipped (scalar cond)."""
        used_slots = jnp.max(trials.snaps.count)
        evaluate = jax.vmap(self._evaluate_slot, in_axes=(0, None))

        def one(j, t):
            return jax.lax.cond(j < used_slots, evaluate, lambda t, j: t, t, j)

        trials = jax.lax.fori_loop(0, self.n_slots, one, trials)
        snaps = trials.snaps
        return trials.replace(snaps=Snapshots(snaps.params, jnp.full_like(snaps.test_index, NO_TEST),
                                              jnp.zeros_like(snaps.count)))

    def _learn(self, learner, upd_keys, iteration):
        """``gradient_steps`` updates of every trial's learner, one per slice of the iteration's noise."""
        step = lambda l, u: (jax.vmap(self.learner.update)(l, u), None)
        return jax.lax.scan(step, learner, self._update_noise(upd_keys, iteration), length=self.gradient_steps)[0]

    def _run_chunk(self, state: TrainState) -> TrainState:
        act_noise, upd_keys = self._noise(state.trials, state.chunk)
        vstep = jax.vmap(self._env_step, in_axes=(0, 0, None))

        def iteration(carry, noise):
            trials, step = carry
            act, i = noise

            def inner(c, n):
                t, k = c
                return (vstep(t, n, k), k + 1), None

            (trials, step), _ = jax.lax.scan(inner, (trials, step), act)
            trials = jax.lax.cond(jnp.any(trials.pending_test != NO_TEST),
                                  jax.vmap(self._snapshot), lambda t: t, trials)
            # one snapshot per trial per iteration at most (checked in __init__), so none is ever lost; the
            # chunk's last iteration evaluates what is left (one copy of the tests in the program, not two)
            used = jnp.max(trials.snaps.count)
            due = (used >= self.n_slots) | ((i == self.iters - 1) & (used > 0))
            trials = jax.lax.cond(due, self._evaluate, lambda t: t, trials)
            learner = jax.lax.cond(step >= self.learning_starts, self._learn, lambda l, *_: l, trials.learner,
                                   upd_keys, i)
            return (trials.replace(learner=learner), step), None

        (trials, step), _ = jax.lax.scan(iteration, (state.trials, state.step),
                                         (act_noise, jnp.arange(self.iters, dtype=jnp.uint32)))
        return TrainState(trials=trials, step=step, chunk=state.chunk + 1)

    def _run_lanes(self, state: TrainState, lanes: jax.Array) -> TrainState:
        """One chunk of the trials ``lanes`` only (int32[B]; an index past the last trial pads the batch:
        it runs a copy of the last trial and its results are dropped); the other trials are left as they are."""
        part = jax.tree.map(lambda x: jnp.take(x, lanes, axis=0, mode="clip"), state.trials)
        out = self._run_chunk(state.replace(trials=part))
        trials = jax.tree.map(lambda x, y: x.at[lanes].set(y, mode="drop"), state.trials, out.trials)
        return out.replace(trials=trials)

    def lanes_to_run(self, state: TrainState) -> np.ndarray | None:
        """The trials still short of their episodes, padded to their ``batch_bucket``, once that batch is
        smaller than all trials (384 lanes: 256 once 256 or fewer run, 192 once 192 do); None (run them
        all) before, with ``drop_finished`` off, or when the trials are sharded over several devices. A
        finished trial records nothing more (module docstring), so leaving it out changes no result; the
        batch sizes are few, so few programs compile."""
        if not self.drop_finished or len(state.trials.episodes.sharding.device_set) > 1:
            return None
        live = np.flatnonzero(self._live(*self._counts(state)))
        n = len(state.trials.episodes)
        size = batch_bucket(len(live))
        if size >= n:
            return None
        return np.concatenate([live, np.full(size - len(live), n)]).astype(np.int32)

    # -- placement and compilation ---------------------------------------------------------------
    def place(self, state: TrainState, devices=None) -> TrainState:
        """Shard the trials axis of ``state`` over ``devices`` (default: every local device) with
        ``jax.sharding``; the step counters are replicated. Every per-trial computation is local to its
        shard; only the scalar conditions (any test due? how many snapshot slots used?) are reduced
        across devices, so the results equal a one-device run. ``len(devices)`` must divide the trials."""
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        devices = trial_devices(devices)
        n_trials = jax.tree.leaves(state.trials)[0].shape[0]
        if n_trials % len(devices):
            raise ConfigError(f"{n_trials} trials cannot be split evenly over {len(devices)} devices")
        mesh = Mesh(np.asarray(devices), ("trials",))
        by_trial, replicated = NamedSharding(mesh, PartitionSpec("trials")), NamedSharding(mesh, PartitionSpec())
        return TrainState(trials=jax.device_put(state.trials, by_trial),
                          step=jax.device_put(state.step, replicated), chunk=jax.device_put(state.chunk, replicated))

    def compile(self, state: TrainState) -> float:
        """Compile the chunk ahead of time for ``state``'s shapes and placement (the output keeps the
        input's sharding, so every chunk reuses this one executable); returns the seconds it took."""
        start = time.perf_counter()
        shardings = jax.tree.map(lambda x: x.sharding, state)
        self._chunk = jax.jit(self._run_chunk, donate_argnums=0, out_shardings=shardings).lower(state).compile()
        return time.perf_counter() - start

    def release_programs(self) -> None:
        """Drop this trainer's compiled programs (a finished stage's). A run of many trainers (a benchmark's
        dozens) would otherwise keep every one in memory, and past ~40 programs LLVM ran out of memory maps
        for their code (vm.max_map_count). A later call compiles again."""
        for f in (self._chunk, self._lanes_chunk, self._init):
            if hasattr(f, "clear_cache"):
                f.clear_cache()
        self._chunk = jax.jit(self._run_chunk, donate_argnums=0)

    # -- host loop ------------------------------------------------------------------------------
    def max_chunks(self) -> int:
        max_steps = self.cfg.episodes * self.env.horizon
        return math.ceil(max_steps / self.chunk_steps) + 1

    def _progress(self, state: TrainState) -> np.ndarray:
        """Episodes per trial, a stopped trial's counted as the whole budget."""
        episodes, first = self._counts(state)
        return np.where(self._live(episodes, first), np.minimum(episodes, self.cfg.episodes), self.cfg.episodes)

    def done(self, state: TrainState) -> bool:
        return bool(np.min(self._progress(state)) >= self.cfg.episodes)

    def run_chunk(self, state: TrainState) -> TrainState:
        lanes = self.lanes_to_run(state)
        return self._chunk(state) if lanes is None else self._lanes_chunk(state, lanes)

    def train(self, keys: jax.Array, progress: Callable | None = None, state: TrainState | None = None,
              on_chunk: Callable | None = None, env_params=None) -> TrainState:
        """Run chunks until every trial has ``episodes`` episodes. ``progress(info)`` after each chunk; its
        ``eta`` (seconds to go, from the slowest trial's pace) is None until that trial has moved."""
        state = self.init(keys, env_params) if state is None else state
        start, frac0 = time.perf_counter(), self._fraction_done(state)
        while not self.done(state):
            if int(state.chunk) >= self.max_chunks():
                raise RuntimeError("episode budget not reached within the step bound; this is a bug")
            state = self.run_chunk(state)
            if on_chunk is not None:
                on_chunk(state)
            if progress is not None:
                eps = self._progress(state)
                elapsed, frac = time.perf_counter() - start, self._fraction_done(state)
                progress({"chunk": int(state.chunk), "episodes_min": int(eps.min()), "episodes_mean": float(eps.mean()),
                          "episodes_total": self.cfg.episodes, "elapsed": elapsed,
                          "eta": seconds_to_go(elapsed, frac0, frac), "step": int(state.step)})
        return state

    def _fraction_done(self, state: TrainState) -> float:
        """How far the slowest trial is through its episodes (a resumed run starts part-way)."""
        return float(self._progress(state).min() / self.cfg.episodes)

    def results(self, state: TrainState) -> dict:
        """Per-trial numpy results (leading trials axis) plus episodes_to_optimal as a list. With
        ``stop_at_optimal``, the episodes and tests a trial did not run are nan (curves as float)."""
        t = jax.device_get(state.trials)
        n, nt = self.cfg.episodes, self.n_tests
        if self.cfg.stop_at_optimal:
            ran = np.asarray(t.episodes)[:, None]
            unrun = lambda x, count: np.where(np.arange(x.shape[1]) < count, x.astype(np.float32), np.nan)
            t = t.replace(**{k: unrun(getattr(t, k), ran) for k in ("train_return", "train_length")},
                          **{k: unrun(getattr(t, k), ran // self.cfg.test_every)
                             for k in ("test_return", "test_length", "test_coverage")})
        first = np.asarray(t.first_optimal_test)
        eto = [None if f == NEVER else int((f + 1) * self.cfg.test_every) for f in first]
        solved = t.test_solved[:, :nt]
        first_test = lambda rows: [int((np.argmax(row) + 1) * self.cfg.test_every) if row.any() else None
                                   for row in rows]
        return {
            "train_return": t.train_return[:, :n], "train_length": t.train_length[:, :n],
            "test_return": t.test_return[:, :nt], "test_length": t.test_length[:, :nt],
            "test_optimal": t.test_optimal[:, :nt], "test_solved": solved,
            "test_episode": (np.arange(nt) + 1) * self.cfg.test_every,
            "best_return": t.best_return, "best_length": t.best_length, "best_test": t.best_test,
            "test_start_optimal": t.test_start_optimal[:, :nt], "test_coverage": t.test_coverage[:, :nt],
            "best_params": t.best_params, "best_coverage": t.best_coverage, "env_steps": t.env_steps,
            "episodes_to_optimal": eto, "episodes_to_solved": first_test(solved),
            "episodes_to_start_optimal": first_test(t.test_start_optimal[:, :nt]),
        }
