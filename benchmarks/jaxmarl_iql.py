"""JaxMARL's IQL, its method and structure, on jaxmarl's installable pieces (benchmark peer, issue 7).

The ``jaxmarl`` wheel (0.2.0) ships the environments, ``MultiAgentEnv`` and the baseline wrappers
(``CTRolloutManager``, ``LogWrapper``), but not the training scripts: those live in the GitHub
repository (``baselines/QLearning/*.py``, run through hydra and wandb), not on PyPI. This file is our
own rendition, written for this benchmark, of the feed-forward Q-learning script's structure
(``baselines/QLearning/ql_ff.py`` with ``LOSS_TYPE: iql``; the ``iql_rnn.py`` exploration):

* ``make_train(config, env)`` returns ``train(rng)``; seeds run as ``jax.jit(jax.vmap(train))(rngs)``.
* The env is ``LogWrapper`` inside ``CTRolloutManager`` (which pads observations, appends a one-hot
  agent id, adds ``obs["__all__"]`` and auto-resets).
* One update step = ``NUM_STEPS`` env steps of ``NUM_ENVS`` envs in a ``lax.scan``, epsilon-greedy
  with a linear schedule over update steps (``optax.linear_schedule``) and random actions drawn with
  ``jax.random.choice`` over the valid actions, keys split every step; the whole ``Timestep`` (obs
  dict including ``__all__``, actions, rewards, dones) goes into a flashbax flat buffer; then, under
  ``lax.cond(can_sample & timesteps > LEARNING_STARTS)``, ``NUM_MINI_EPOCHS`` gradient steps on
  ``BUFFER_BATCH_SIZE`` pairs (``first``, ``second``) with the target
  ``r + (1 - done) * gamma * max_a Q_target(second.obs)``; a ``TrainState`` with
  ``clip_by_global_norm`` + the optimizer; the target network copied (``incremental_update`` with
  ``TAU``) when ``n_updates % TARGET_UPDATE_INTERVAL == 0``.
* Parameter sharing (JaxMARL's IQL default, ``iql_ps``): one network for both agents, told apart by
  the agent id; ``PARAMETER_SHARING=False`` gives one network and one optimizer per agent.
* A greedy test env (``CTRolloutManager`` of batch 1) stepped once per update step with the test
  policy, as the script does.

Where we depart from the script, and why:
* The buffer is added to as sequences (``add_sequences=True, add_batch_size=NUM_ENVS``). The
  script adds the ``NUM_STEPS x NUM_ENVS`` transitions as one flat batch of rows, so that the flat
  buffer's (``first``, ``second``) pairs are the same (step, env) slot of two consecutive update
  steps, ``NUM_STEPS`` env steps apart, rather than consecutive steps (as we read flashbax 0.1.3's
  ``make_flat_buffer``). The cost is the same; the pairs here are the true transitions.
* Exploration draws a key per agent (as ``iql_rnn.py`` does; ``ql_ff.py`` gives both agents one key).
* The test policy is refreshed, and the test env reset, every ``TEST_EVERY_EPISODES`` training
  episodes (jaxusar's cadence), not every ``TEST_POLICY_UPDATE_INTERVAL`` updates, so that
  episodes-to-optimal is counted the same way on both sides. A refresh while the previous test is
  still running abandons it (counted in ``tests_abandoned``).
* No wandb, no hydra: ``config`` is a dict with the script's key names.

Settings are the caller's (``benchmarks/vs_jaxmarl.py`` matches them to jaxusar's IQL).

Run alone, it trains on any map through the package's adapter ``jaxusar.interop.JaxMARLEnv`` (JaxMARL's
``MultiAgentEnv`` API: what a JaxMARL user's learner sees), all seeds in one call:

    python benchmarks/jaxmarl_iql.py --map two_rooms_rubble --seeds 2 --steps 40000
    python benchmarks/jaxmarl_iql.py --map minimap --horizon 100 --set TEST_EVERY_EPISODES=20 --out r.json

It prints the wall time (compile + run), the training episodes, the greedy tests' returns, and the training
episodes to the first test with a triage and to the first optimal test (where the map's optimum is known:
``--optimal-steps``, or the planner's exact optimum on maps with fixed victims).
"""

from __future__ import annotations

import argparse
import ast
import json
import time
from pathlib import Path
from typing import Any, Sequence

import chex
import flashbax as fbx
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training.train_state import TrainState
from jaxmarl.wrappers.baselines import CTRolloutManager, LogWrapper

DEFAULTS = dict(
    NUM_ENVS=1, NUM_STEPS=8, TOTAL_TIMESTEPS=300_000, BUFFER_SIZE=50_000, BUFFER_BATCH_SIZE=32, HIDDEN=(32, 32),
    EPS_START=1.0, EPS_FINISH=0.05, EPS_DECAY=50_000 / 300_000, MAX_GRAD_NORM=10.0, TARGET_UPDATE_INTERVAL=250,
    TAU=1.0, NUM_MINI_EPOCHS=1, LR=5e-4, OPTIMIZER="adam", LOSS="huber", LEARNING_STARTS=1000, GAMMA=0.99,
    PARAMETER_SHARING=True, TEST_EVERY_EPISODES=50, OPTIMAL_STEPS=18, MIN_EPISODE_STEPS=18,
)


class QNetwork(nn.Module):
    action_dim: int
    hidden: Sequence[int]

    @nn.compact
    def __call__(self, x):
        for width in self.hidden:
            x = nn.relu(nn.Dense(width)(x))
        return nn.Dense(self.action_dim)(x)


@chex.dataclass(frozen=True)
class Timestep:
    obs: dict
    actions: dict
    rewards: dict
    dones: dict


class CustomTrainState(TrainState):
    target_network_params: Any
    timesteps: int = 0
    n_updates: int = 0
    grad_steps: int = 0


@chex.dataclass
class TestState:
    params: Any
    obs: dict
    env_state: Any
    active: jax.Array
    ret: jax.Array
    length: jax.Array
    index: jax.Array         # which test (snapshot number) is running
    lengths: jax.Array       # int32[max_tests]: test episode lengths (0 = not run)
    returns: jax.Array       # float32[max_tests]
    terminated: jax.Array    # bool[max_tests]
    abandoned: jax.Array


def make_train(config: dict, env):
    c = {**DEFAULTS, **config}
    c["NUM_UPDATES"] = int(c["TOTAL_TIMESTEPS"] // c["NUM_STEPS"] // c["NUM_ENVS"])
    eps_scheduler = optax.linear_schedule(c["EPS_START"], c["EPS_FINISH"], c["EPS_DECAY"] * c["NUM_UPDATES"])
    max_tests = int(c["TOTAL_TIMESTEPS"] // (c["TEST_EVERY_EPISODES"] * c["MIN_EPISODE_STEPS"])) + 1
    env = LogWrapper(env)
    agents = env.agents
    sharing = bool(c["PARAMETER_SHARING"])

    def batchify(x: dict):
        return jnp.stack([x[a] for a in agents], axis=0)

    def unbatchify(x):
        return {a: x[i] for i, a in enumerate(agents)}

    def greedy(q_vals, valid):
        return jnp.argmax(jnp.where(valid.astype(bool), q_vals, -1e6), axis=-1)

    def eps_greedy(rng, q_vals, eps, valid):
        rng_a, rng_e = jax.random.split(rng)
        greedy_actions = greedy(q_vals, valid)
        random_actions = jax.random.choice(rng_a, jnp.arange(valid.shape[-1]), shape=greedy_actions.shape,
                                           p=valid / valid.sum())
        return jnp.where(jax.random.uniform(rng_e, greedy_actions.shape) < eps, random_actions, greedy_actions)

    def train(rng):
        wrapped_env = CTRolloutManager(env, batch_size=c["NUM_ENVS"])
        test_env = CTRolloutManager(env, batch_size=1)
        network = QNetwork(action_dim=wrapped_env.max_action_space, hidden=tuple(c["HIDDEN"]))
        n_agents = len(agents)

        def q_values(params, obs):  # obs [n_agents, ..., obs_size] -> [n_agents, ..., A]
            if sharing:
                return jax.vmap(network.apply, in_axes=(None, 0))(params, obs)
            return jax.vmap(network.apply)(params, obs)

        def create_agent(rng):
            x = jnp.zeros((wrapped_env.obs_size,))
            if sharing:
                params = network.init(rng, x)
            else:
                params = jax.vmap(network.init, in_axes=(0, None))(jax.random.split(rng, n_agents), x)
            optimizer = optax.adam if c["OPTIMIZER"] == "adam" else optax.radam
            tx = optax.chain(optax.clip_by_global_norm(c["MAX_GRAD_NORM"]), optimizer(learning_rate=c["LR"]))
            if sharing:
                return CustomTrainState.create(apply_fn=network.apply, params=params, target_network_params=params,
                                               tx=tx)
            # one optimizer state per agent (a leading agent axis), so clipping is per agent
            return CustomTrainState(step=0, apply_fn=network.apply, params=params, target_network_params=params,
                                    tx=tx, opt_state=jax.vmap(tx.init)(params))

        rng, _rng = jax.random.split(rng)
        train_state = create_agent(_rng)

        buffer = fbx.make_flat_buffer(max_length=int(c["BUFFER_SIZE"]), min_length=int(c["BUFFER_BATCH_SIZE"]),
                                      sample_batch_size=int(c["BUFFER_BATCH_SIZE"]), add_sequences=True,
                                      add_batch_size=int(c["NUM_ENVS"]))
        rng, _rng = jax.random.split(rng)
        _obs, _env_state = wrapped_env.batch_reset(_rng)
        _actions = {a: wrapped_env.batch_sample(_rng, a) for a in agents}
        _obs, _, _rewards, _dones, _ = wrapped_env.batch_step(_rng, _env_state, _actions)
        example = Timestep(obs=_obs, actions=_actions, rewards=_rewards, dones=_dones)
        buffer_state = buffer.init(jax.tree.map(lambda x: x[0], example))
        valid = batchify(wrapped_env.valid_actions_oh)

        def loss_fn(params, target_params, first, second, q_fn):
            """TD loss over a batch of rows (leading [agents] axis under sharing; one agent's rows otherwise)."""
            q_next = jnp.max(q_fn(target_params, second["obs"]), axis=-1)
            target = first["rewards"] + (1 - first["dones"]) * c["GAMMA"] * q_next
            q_vals = q_fn(params, first["obs"])
            chosen = jnp.take_along_axis(q_vals, first["actions"][..., None], axis=-1)[..., 0]
            td = chosen - jax.lax.stop_gradient(target)
            per = optax.huber_loss(td) if c["LOSS"] == "huber" else td ** 2
            return per.mean(), chosen.mean()

        def rows(part):
            return {"obs": batchify(part.obs), "actions": batchify(part.actions), "rewards": batchify(part.rewards),
                    "dones": batchify(part.dones).astype(jnp.float32)}

        def gradient_step(train_state, first, second):
            grad_fn = jax.value_and_grad(loss_fn, has_aux=True)
            if sharing:
                (loss, qvals), grads = grad_fn(train_state.params, train_state.target_network_params, first, second,
                                               q_values)
                return train_state.apply_gradients(grads=grads), loss, qvals
            (loss, qvals), grads = jax.vmap(grad_fn, in_axes=(0, 0, 0, 0, None))(
                train_state.params, train_state.target_network_params, first, second, network.apply)
            updates, opt_state = jax.vmap(train_state.tx.update)(grads, train_state.opt_state, train_state.params)
            train_state = train_state.replace(params=optax.apply_updates(train_state.params, updates),
                                              opt_state=opt_state, step=train_state.step + 1)
            return train_state, loss.mean(), qvals.mean()

        def test_step(test: TestState, rng):
            q_vals = q_values(test.params, batchify(test.obs))
            actions = unbatchify(jax.vmap(greedy)(q_vals, valid))
            obs, env_state, rewards, dones, info = test_env.batch_step(rng, test.env_state, actions)
            ended = test.active & dones["__all__"][0]
            ret, length = test.ret + rewards[agents[0]][0], test.length + 1
            idx = jnp.where(ended, test.index, max_tests)
            return test.replace(
                obs=obs, env_state=env_state, active=test.active & ~ended,
                ret=jnp.where(test.active, ret, test.ret), length=jnp.where(test.active, length, test.length),
                lengths=test.lengths.at[idx].set(length, mode="drop"),
                returns=test.returns.at[idx].set(ret, mode="drop"),
                terminated=test.terminated.at[idx].set(info["terminated"][0], mode="drop"))

        def refresh_test(test: TestState, params, due, index, rng):
            obs, env_state = test_env.batch_reset(rng)
            pick = lambda new, old: jax.tree.map(lambda x, y: jnp.where(due, x, y), new, old)
            return test.replace(params=pick(params, test.params), obs=pick(obs, test.obs),
                                env_state=pick(env_state, test.env_state), active=test.active | due,
                                ret=jnp.where(due, 0.0, test.ret), length=jnp.where(due, 0, test.length),
                                index=jnp.where(due, index, test.index),
                                abandoned=test.abandoned + (due & test.active))

        def update_step(runner_state, _):
            train_state, buffer_state, expl_state, test, episodes, rng = runner_state

            def step_env(carry, _):
                last_obs, env_state, rng = carry
                rng, rng_a, rng_s = jax.random.split(rng, 3)
                q_vals = q_values(train_state.params, batchify(last_obs))  # [n_agents, num_envs, A]
                eps = eps_scheduler(train_state.n_updates)
                keys = jax.random.split(rng_a, n_agents)
                actions = unbatchify(jax.vmap(eps_greedy, in_axes=(0, 0, None, 0))(keys, q_vals, eps, valid))
                obs, env_state, rewards, dones, infos = wrapped_env.batch_step(rng_s, env_state, actions)
                timestep = Timestep(obs=last_obs, actions=actions, rewards=rewards, dones=dones)
                return (obs, env_state, rng), (timestep, infos)

            rng, _rng = jax.random.split(rng)
            (obs, env_state, _), (timesteps, infos) = jax.lax.scan(step_env, (*expl_state, _rng), None, c["NUM_STEPS"])
            train_state = train_state.replace(timesteps=train_state.timesteps + c["NUM_STEPS"] * c["NUM_ENVS"])
            new_episodes = episodes + timesteps.dones["__all__"].sum()  # training episodes, all envs

            # buffer: [num_steps, num_envs, ...] -> [num_envs, num_steps, ...] sequences
            buffer_state = buffer.add(buffer_state, jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), timesteps))

            def learn_phase(carry, _):
                train_state, rng = carry
                rng, _rng = jax.random.split(rng)
                minibatch = buffer.sample(buffer_state, _rng).experience
                train_state, loss, qvals = gradient_step(train_state, rows(minibatch.first), rows(minibatch.second))
                return (train_state.replace(grad_steps=train_state.grad_steps + 1), rng), (loss, qvals)

            rng, _rng = jax.random.split(rng)
            learn = buffer.can_sample(buffer_state) & (train_state.timesteps > c["LEARNING_STARTS"])
            (train_state, _), (loss, qvals) = jax.lax.cond(
                learn,
                lambda ts, r: jax.lax.scan(learn_phase, (ts, r), None, c["NUM_MINI_EPOCHS"]),
                lambda ts, r: ((ts, r), (jnp.zeros(c["NUM_MINI_EPOCHS"]), jnp.zeros(c["NUM_MINI_EPOCHS"]))),
                train_state, _rng)
            train_state = jax.lax.cond(
                train_state.n_updates % c["TARGET_UPDATE_INTERVAL"] == 0,
                lambda ts: ts.replace(target_network_params=optax.incremental_update(
                    ts.params, ts.target_network_params, c["TAU"])),
                lambda ts: ts, train_state)
            train_state = train_state.replace(n_updates=train_state.n_updates + 1)

            rng, rng_t, rng_r = jax.random.split(rng, 3)
            test = test_step(test, rng_t)
            every = c["TEST_EVERY_EPISODES"]
            due = (new_episodes // every) > (episodes // every)
            test = refresh_test(test, train_state.params, due, new_episodes // every - 1, rng_r)

            metrics = {"returns": jnp.nanmean(jnp.where(infos["returned_episode"], infos["returned_episode_returns"],
                                                        jnp.nan)),
                       "env_step": train_state.timesteps, "loss": loss.mean(), "qvals": qvals.mean()}
            return (train_state, buffer_state, (obs, env_state), test, new_episodes, rng), metrics

        rng, _rng = jax.random.split(rng)
        expl_state = wrapped_env.batch_reset(_rng)
        rng, _rng = jax.random.split(rng)
        test_obs, test_env_state = test_env.batch_reset(_rng)
        test = TestState(params=train_state.params, obs=test_obs, env_state=test_env_state,
                         active=jnp.zeros((), bool), ret=jnp.zeros(()), length=jnp.zeros((), jnp.int32),
                         index=jnp.zeros((), jnp.int32), lengths=jnp.zeros((max_tests,), jnp.int32),
                         returns=jnp.zeros((max_tests,)), terminated=jnp.zeros((max_tests,), bool),
                         abandoned=jnp.zeros((), jnp.int32))
        runner_state = (train_state, buffer_state, expl_state, test, jnp.zeros((), jnp.int32), rng)
        runner_state, metrics = jax.lax.scan(update_step, runner_state, None, c["NUM_UPDATES"])
        train_state, _, _, test, episodes, _ = runner_state
        return {"episodes": episodes, "test_lengths": test.lengths, "test_returns": test.returns,
                "test_terminated": test.terminated, "tests_abandoned": test.abandoned,
                "grad_steps": train_state.grad_steps, "metrics": metrics}

    return train


def episodes_to(results: dict, every: int, optimal_steps: int) -> dict:
    """Per seed: training episodes at the first optimal test and at the first test with a triage."""
    lengths, returns, term = (np.asarray(results[k]) for k in ("test_lengths", "test_returns", "test_terminated"))
    out = {"optimal": [], "first_triage": []}
    for s in range(lengths.shape[0]):
        opt = np.flatnonzero(term[s] & (lengths[s] > 0) & (lengths[s] <= optimal_steps))
        tri = np.flatnonzero((lengths[s] > 0) & (returns[s] > 0))
        out["optimal"].append(int((opt[0] + 1) * every) if len(opt) else None)
        out["first_triage"].append(int((tri[0] + 1) * every) if len(tri) else None)
    return out


def optimum(env, given: int | None) -> int | None:
    """Fewest team steps to triage every victim: ``given``, else the planner's exact search where it
    runs (fixed victims, a joint search within its limit), else None."""
    if given is not None:
        return given
    from jaxusar import planning

    try:
        return int(planning.optimal_team_steps(env))
    except (ValueError, planning.SearchTooLarge) as e:
        print(f"no exact optimum for {env.layout.name!r} ({type(e).__name__}): episodes to optimal not reported",
              flush=True)
        return None


def main(argv=None):
    from jaxusar import envs
    from jaxusar.interop import JaxMARLEnv

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--map", default="two_rooms", help="a jaxusar map (jaxusar.envs.available_layouts())")
    p.add_argument("--horizon", type=int, default=300)
    p.add_argument("--observation", choices=["full", "view"], help="default: the map's own")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--steps", type=int, default=40_000, help="env steps per seed (TOTAL_TIMESTEPS)")
    p.add_argument("--no-sharing", action="store_true", help="one network per agent (default: JaxMARL's sharing)")
    p.add_argument("--optimal-steps", type=int, help="the map's optimum in team steps (default: the planner's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help=f"any other setting of {sorted(DEFAULTS)} (a Python literal)")
    p.add_argument("--out", help="write the results as JSON here")
    args = p.parse_args(argv)

    overrides = {"horizon": args.horizon, **({"observation": args.observation} if args.observation else {})}
    adapter = JaxMARLEnv(envs.make(args.map, **overrides))
    optimal = optimum(adapter.env, args.optimal_steps)
    config = {"TOTAL_TIMESTEPS": args.steps, "PARAMETER_SHARING": not args.no_sharing,
              "OPTIMAL_STEPS": optimal, "MIN_EPISODE_STEPS": optimal or 1}
    for item in args.set:
        key, _, value = item.partition("=")
        if key not in DEFAULTS:
            raise SystemExit(f"--set {item}: unknown setting {key!r}; known: {sorted(DEFAULTS)}")
        config[key] = ast.literal_eval(value)
    every = config.get("TEST_EVERY_EPISODES", DEFAULTS["TEST_EVERY_EPISODES"])

    start = time.perf_counter()
    train = jax.jit(jax.vmap(make_train(config, adapter)))
    rngs = jax.random.split(jax.random.PRNGKey(0), args.seeds)
    compiled = train.lower(rngs).compile()
    compile_s = time.perf_counter() - start
    t = time.perf_counter()
    out = jax.device_get(jax.block_until_ready(compiled(rngs)))
    run_s = time.perf_counter() - t
    wall_s = time.perf_counter() - start

    lengths, returns = np.asarray(out["test_lengths"]), np.asarray(out["test_returns"])
    ran = lengths > 0
    eto = episodes_to(out, every, optimal if optimal is not None else -1)
    result = {
        "map": args.map, "env": repr(adapter.env), "agents": adapter.agents, "obs_dim": adapter.obs_dim,
        "optimal_team_steps": optimal, "seeds": args.seeds, "env_steps_per_seed": args.steps,
        "config": {**DEFAULTS, **config}, "wall_s": wall_s, "compile_s": compile_s, "run_s": run_s,
        "env_steps_per_s": args.seeds * args.steps / wall_s,
        "training_episodes": np.asarray(out["episodes"]).tolist(),
        "tests_run": ran.sum(1).tolist(), "tests_abandoned": np.asarray(out["tests_abandoned"]).tolist(),
        "best_test_return": [float(r[m].max()) if m.any() else None for r, m in zip(returns, ran)],
        "last_test_return": [float(r[m][-1]) if m.any() else None for r, m in zip(returns, ran)],
        "episodes_to_first_triage": eto["first_triage"],
        "episodes_to_optimal": eto["optimal"] if optimal is not None else None,
    }
    try:
        from jaxusar.experiments.train import environment_info

        result["environment"] = environment_info()
    except ImportError:
        pass
    print(f"JaxMARL IQL ({'shared' if not args.no_sharing else 'per-agent'} network) on {adapter.env!r} through "
          f"jaxusar.interop.JaxMARLEnv: {args.seeds} seeds x {args.steps} env steps")
    print(f"wall {wall_s:.1f}s (compile {compile_s:.1f}s, run {run_s:.1f}s), "
          f"{result['env_steps_per_s']:,.0f} env steps/s")
    for key in ("training_episodes", "tests_run", "best_test_return", "last_test_return",
                "episodes_to_first_triage", "episodes_to_optimal"):
        print(f"  {key:26} {result[key]}")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=2, default=float))
        print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
