"""The coordinator: SMDP Q-learning over joint options on the graph view (paper Sec. IV-C).

The coordinator sees the abstract state (each agent's region one-hot, the triaged flags, on a map with
rubble each rubble group's cleared flag: rubble is part of the floor plan every agent sees; where victims
are drawn at reset, instead of triaged flags each room's flag (every slot of it done: ``flags``) and the
known victims per room and kind, capped at ``KNOWN_CAP``; where critical victims expire, a coarse clock;
never an unseen victim) and picks a
joint option (one option per agent: 4 x 4 = 16 on the two-rooms map). ``coordinator.kind: flat`` (the
paper) has one Q-value per joint option, options ^ medics of them (refused past ``max_joint_options``:
office would need 15^4 = 50,625); ``factored`` has one option head per medic, their values summed
(``core.learners.FactoredDQN``, value decomposition), each medic's choice masked to the options it may
start, so its parameters and compute grow linearly in the medics; both learn from the same SMDP target.
The agents run their trained sub-policies greedily (as tables of their greedy actions,
``subpolicies.greedy_tables``: a look-up a step, not a network per agent) in the real team env until the
first agent's option terminates (or the episode ends); then all options terminate and the coordinator
decides again: one SMDP transition of k steps.

Decisions left open by the paper, made here:

* Invalid joint option (some agent's option has its initiation set unmet, or that agent has no
  sub-policy for it): reward ``invalid_penalty`` (default -100), time advances one primitive step with
  every agent standing still, and the coordinator decides again. So an episode still ends at the horizon.
  For learning, that transition is a dead end: its target is the penalty alone, with no bootstrap.
  (With a bootstrap, a greedy choice of an invalid option repeats in the unchanged state, and the
  penalties compound into Q-values near -100 / (1 - gamma) for every option; measured: no trial learned.)
* An agent for which no option is available (e.g. it has triaged the victim of its room and the other
  victim is being handled) is idle: its part of the joint option is ignored and it does TRIAGE, a no-op
  unless it faces an untriaged victim. A joint option is valid when every non-idle agent's part is valid.
* Exploration: random picks are drawn among the valid joint options only; the greedy choice ranges over
  all of them, so the greedy policy must learn validity from the penalty, as in the paper. (Random
  picks over all 16 made a decision sequence mostly of invalid choices that ate the epsilon schedule.)
  The SMDP target maximises over the joint options valid at the next decision. (The factored
  coordinator masks its greedy choice too: each medic's head only ranks that medic's valid options.)
* Options also terminate after ``option_timeout`` primitive steps (default: 1.5x the longest optimal
  option path on the map, at least 50: 50 on two_rooms, well above any optimal sub-task path there): an
  imperfect sub-policy can loop from a state it rarely saw, and without a timeout one such loop ate the
  rest of the episode (measured: most of 300 steps).
* Medics in each other's way (not in the paper: two medics, two rooms): the sub-policies are trained
  alone and an agent cannot enter a cell another holds, so two medics meeting head-on in a one-wide
  corridor or door stand there until the timeout. ``block_patience`` (off by default, 0) ends the
  options once an agent has been stopped by another that many times without moving, so the coordinator
  decides again at once; ``features: cells`` lets it see where in a region each medic stands, which a
  region one-hot cannot say (who of two medics in one corridor is east of the other). In the open, the
  same meeting ends in a standstill too (each sub-policy's shortest way is straight ahead): ``dodge``
  (on by default where rubble lies, where agents wait beside the rubble in others' way) makes a stopped
  agent step aside, TURN_RIGHT then FORWARD, before its sub-policy acts again (measured on a drawn map
  with two one-wide rubbled doorways: 0/8 -> 8/8 trials solved over exact sub-policies).
* When options end (the paper, Sec. IV-C: all of them, when the first one does; ``termination: all``):
  with four medics some option ends every few steps, and re-choosing every medic's option each time
  made the medics change course over and over (measured on office). ``termination: own`` lets each
  option run to its own end (its condition, the timeout counted over the decisions it outlives, or a
  block); the running options are part of the abstract state, and a busy medic's only valid choice is
  its running option, so the greedy choice, exploration and the SMDP target's max all hold it.
* Reward: the team reward of the k steps; the SMDP row stores its in-option discounted sum
  sum_i gamma^i r_{t+i} and its own discount gamma^k, so the shared target r + discount * max_valid Q is
  the SMDP target (Sutton, Precup and Singh 1999, eq. 8), and an n-step return chains whole options.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxusar.algos.options import TRIAGE as OPTION_TRIAGE
from jaxusar.algos.options import Options
from jaxusar.config import CoordinatorConfig, DQNConfig
from jaxusar.core.learners import FactoredDQN, IndependentDQN, default_row, dqn_target
from jaxusar.envs.usar import CRITICAL, DIR_DELTA, FORWARD, TRIAGE, TURN_RIGHT, EnvState, USAREnv

CLOCK_BINS = 4  # where critical victims expire, the abstract state's clock: t in quarters of their life
KNOWN_CAP = 3  # where victims are drawn, the abstract state counts the known victims per room and kind up to this
ALGORITHM = "hierarchical"  # `jaxusar train hierarchical`: sub-policies, then the coordinator
EXPERIMENT = "jaxusar.experiments.hierarchical"
DESCRIPTION = "The paper's method (Sec. IV): DQN option sub-policies on pseudo-rewards, then this SMDP coordinator."

DEFAULTS = {
    # sub-policies (paper Fig. 4): a test every 10 episodes, up to ~600 episodes each. Chosen on tuning
    # seeds 1000-1001 (benchmarks/README.md, "Ablation"), judged by the fraction of each option's initiation
    # states from which the greedy policy is optimal: rewards scaled to ~1 (Q near the network's initial
    # scale), an update every env step on batches of 64, 3-step returns cut where the current greedy policy
    # would act otherwise (no bias from old exploring data), discount 0.95 (errors of the bootstrap fade
    # 5x faster than at 0.99, action gaps as wide as 0.99's at the hall's distances), a decaying learning
    # rate, Double DQN, a Polyak-averaged target net (tau 0.005), and exploration that stays wide (epsilon
    # decays over 100k env steps, ~0.8 at a lane's end): the Q of an action is only learned where it was
    # tried, and the greedy tests, not the exploring episodes, are what counts. A sub-policy stops at its
    # first test optimal from every initiation state. (A map's settings file may set per-task discounts:
    # two_rooms' triage-bottom 0.9.)
    "dqn": {"hidden": [64, 64], "lr": 2e-3, "lr_schedule": "linear", "lr_end": 2e-4, "lr_decay_updates": 20000,
            "gamma": 0.95, "train_every": 1, "batch_size": 64, "tau": 0.005, "n_step": 3,
            "n_step_cut_greedy": True, "reward_scale": 0.01,
            "eps_decay_steps": 100000, "learning_starts": 500, "double_dqn": True},
    "train": {"episodes": 600, "test_every": 10, "chunk_steps": 4000, "stop_at_optimal": True},
    "hierarchical": {"subpolicy_features": "cell", "navigate_start": "initiation"},
}


@struct.dataclass
class MacroState:
    """The team env's state and each medic's running option (-1: none) with the steps it has run: with
    ``termination: own`` a medic's option outlives the decisions made for the others."""

    env: EnvState
    running: jax.Array  # int32[n_agents]
    elapsed: jax.Array  # int32[n_agents]

    agent_pos = property(lambda self: self.env.agent_pos)
    agent_dir = property(lambda self: self.env.agent_dir)
    triaged = property(lambda self: self.env.triaged)
    t = property(lambda self: self.env.t)


@struct.dataclass
class CoordinatorParams:
    """Per-trial data the macro env needs: the trained sub-policies, stacked over tasks."""

    subpolicy: object  # params with a leading task axis


class MacroEnv:
    """The team env seen by the coordinator: one ``step`` = one joint option run to termination.

    ``policy_for`` int[n_agents, R, O] (or [n_agents, O], the same in every region): which sub-policy
    task executes option o for agent i while it is in region q (-1: none); chained navigation changes
    task as the agent crosses regions. ``subpolicy_act(params, obs) -> action[1]`` runs one sub-policy
    greedily; ``observe(pos, dir, flag, goal)`` builds its input, ``option_goals`` int[O] (default 0) the
    goal index each option's sub-policy is told (goal-conditioned navigation). ``factored``: the action is the options
    themselves, int32[n_agents] (a factored coordinator); else one joint-option index, int32[1].
    ``block_patience`` (0: off): the options also end once an active agent has been stopped this many
    times by another (FORWARD into a cell an agent holds) without moving in between. ``dodge``: an agent
    so stopped steps aside (TURN_RIGHT, then FORWARD) before its sub-policy acts again, so two agents
    meeting head-on in the open pass each other, and one walking into an agent that waits goes round it.
    ``cells``: the abstract state also says each medic's row and column (one-hot), not only its region.
    ``own_termination``: a medic's option ends only by its own termination condition (or timeout, or
    block); the coordinator then chooses for the medics whose options ended, the others' running options
    being part of the abstract state and their only valid choice (the paper: every option ends when the
    first one does).
    """

    def __init__(self, env: USAREnv, options: Options, policy_for: np.ndarray, subpolicy_act, observe,
                 gamma: float, invalid_penalty: float, option_timeout: int = 50, factored: bool = False,
                 block_patience: int = 0, cells: bool = False, own_termination: bool = False,
                 option_goals: np.ndarray | None = None, dodge: bool = False, slot_task: np.ndarray | None = None,
                 slot_goal: np.ndarray | None = None, slot_dist: np.ndarray | None = None,
                 slot_every_mode: np.ndarray | None = None):
        self.env, self.options = env, options
        self.option_goals = np.zeros(options.n, np.int32) if option_goals is None else np.asarray(option_goals, np.int32)
        self.n_agents, self.horizon = env.n_agents, env.horizon
        self.n_regions = env.graph.n_regions
        policy_for = np.asarray(policy_for, np.int32)
        if policy_for.ndim == 2:
            policy_for = np.repeat(policy_for[:, None], self.n_regions, 1)
        self.policy_for = policy_for
        # the same task in every region (the paper's adjacent navigation): looked up once per option, not per
        # step, so the sub-policy's params stay loop-invariant inside an option (measured: 4x faster there)
        self.region_invariant = bool((policy_for == policy_for[:, :1]).all())
        self.subpolicy_act, self.observe_agent = subpolicy_act, observe
        self.gamma, self.invalid_penalty = float(gamma), float(invalid_penalty)
        self.option_timeout, self.block_patience = int(option_timeout), int(block_patience)
        self.factored, self.cells, self.own_termination, self.dodge = factored, cells, own_termination, dodge
        self.n_joint = options.n ** env.n_agents
        self.rubble = options.rubble  # None: no rubble, or options without CLEAR (one config)
        self.n_groups = self.rubble.n_groups if self.rubble is not None else 0
        # victims (slots, where they are drawn: ``options.method_env``); the plain rules: a slot is done
        # once its fixed victim is triaged, and the triaged flags are the whole of what the team knows
        self.slots = np.asarray(env.layout.victim_pos, np.int32)
        self.n_slots = len(self.slots)
        self.view = env.observation == "view"
        self.plain = not (env.n_drawn or env.expires or self.view)
        self.slot_flag = options.slot_flag  # drawn victims: TRIAGE-IN-R's flag (its room done) for each slot
        self.drawn = self.slot_flag is not None
        if self.drawn:
            assert all(x is not None for x in (slot_task, slot_goal, slot_dist, slot_every_mode)), \
                "drawn victims: each slot's task, goal, distances and modes (hierarchical.slot_tables)"
            self.slot_task, self.slot_goal, self.slot_dist = (np.asarray(x, np.int32) for x in (slot_task, slot_goal,
                                                                                                 slot_dist))
            self.slot_every_mode = np.asarray(slot_every_mode, bool)
        self.n_flags = int(self.slot_flag.max()) + 1 if self.drawn else self.n_slots
        self.obs_blocks = (self.n_regions,) * env.n_agents + (1,) * self.n_flags + (1,) * self.n_groups
        if self.drawn:  # per room: the known victims to save, regular and critical, capped
            self.obs_blocks += (KNOWN_CAP + 1,) * self.n_flags * 2
        if env.expires:  # a coarse clock: quarters of the time critical victims live, then after
            self.obs_blocks += (CLOCK_BINS + 1,)
        if cells:
            self.obs_blocks += (env.height, env.width) * env.n_agents
        if own_termination:
            self.obs_blocks += (options.n + 1,) * env.n_agents  # the running option, 0: none
        self.obs_dim = sum(self.obs_blocks)
        # joint option index -> per-agent options (agent 0 most significant); the factored one never builds it
        self.joint = None if factored else \
            np.array(list(itertools.product(range(options.n), repeat=env.n_agents)), np.int32)

    def options_of(self, action: jax.Array) -> jax.Array:
        """int32[n_agents]: each agent's option in the coordinator's ``action``."""
        return action if self.factored else jnp.asarray(self.joint)[action[0]]

    # -- abstract state --------------------------------------------------------------------------
    def waiting(self, s: EnvState) -> tuple[jax.Array, jax.Array]:
        """(bool[S], bool[S]): the slots that hold a living untriaged victim, and a critical one."""
        at = jnp.all(s.victim_pos[None] == jnp.asarray(self.slots)[:, None], -1)  # [S, V]: victim v on slot s
        waits = at & ~(s.triaged | s.dead)[None]
        return waits.any(-1), (waits & jnp.asarray(self.env.victim_kind == CRITICAL)[None]).any(-1)

    def flags(self, s: EnvState) -> jax.Array:
        """bool[F]: each TRIAGE option's flag, the options' ``triaged``: its victim's slot done, or where
        victims are drawn its room's every slot done."""
        done = self.slot_done(s)
        if not self.drawn:
            return done
        return ~jnp.zeros(self.n_flags, bool).at[jnp.asarray(self.slot_flag)].max(~done)

    def known(self, s: EnvState) -> tuple[jax.Array, jax.Array]:
        """(bool[S], bool[S]): the slots known to hold a victim to save, and a critical one (under "view":
        seen; never an unseen victim)."""
        waits, critical = self.waiting(s)
        seen = s.seen[self.slots[:, 0], self.slots[:, 1]] if self.view else True
        return waits & seen, critical & seen

    def target_slot(self, s: EnvState, i: int, flag: jax.Array, done: jax.Array) -> jax.Array:
        """int32: the slot TRIAGE-IN-R (flag ``flag``) works on for agent ``i``: among its room's slots not
        done, a known critical victim first, then a known victim, then an unseen slot; the nearest (the slot
        task's distance table, in the rubble's mode) first, then the lowest index. Along a slot's shortest
        path its distance falls by one a step and no other's faster, so the target holds."""
        waits, critical = self.known(s)
        index = self.rubble.mode_of(s.rubble) if self.n_groups else 0
        d = jnp.asarray(self.slot_dist)[:, index, s.agent_pos[i, 0], s.agent_pos[i, 1], s.agent_dir[i]]
        rank = jnp.where(critical, 0, jnp.where(waits, 1, 2)) * (10 * self.horizon) + jnp.where(d >= 0, d, 9 * self.horizon)
        ok = (jnp.asarray(self.slot_flag) == flag) & ~done
        return jnp.argmin(jnp.where(ok, rank, jnp.iinfo(jnp.int32).max)).astype(jnp.int32)

    def slot_done(self, s: EnvState) -> jax.Array:
        """bool[S]: the slots the team knows hold no victim to save: under "view" those seen holding none
        (empty, triaged, dead), else those holding none. The plain rules: the fixed victims' triaged flags."""
        if self.plain:
            return s.triaged
        done = ~self.waiting(s)[0]
        return done & s.seen[self.slots[:, 0], self.slots[:, 1]] if self.view else done

    def observe(self, s: MacroState) -> jax.Array:
        regions = self.env.graph.region_of(s.agent_pos)
        parts = [jax.nn.one_hot(regions, self.n_regions).ravel(), self.flags(s.env).astype(jnp.float32)]
        if self.n_groups:  # each rubble group cleared (rubble is part of the floor plan every agent sees)
            parts.append(((self.config_of(s.env) >> jnp.arange(self.n_groups)) & 1).astype(jnp.float32))
        if self.drawn:  # the known victims per room and kind: never an unseen one
            waits, critical = self.known(s.env)
            for x in (waits & ~critical, critical):
                count = jnp.zeros(self.n_flags, jnp.int32).at[jnp.asarray(self.slot_flag)].add(x.astype(jnp.int32))
                parts.append(jax.nn.one_hot(jnp.minimum(count, KNOWN_CAP), KNOWN_CAP + 1).ravel())
        if self.env.expires:
            quarter = jnp.minimum(s.env.t * CLOCK_BINS // self.env.critical_expires, CLOCK_BINS)
            parts.append(jax.nn.one_hot(quarter, CLOCK_BINS + 1))
        if self.cells:
            parts += [jnp.concatenate([jax.nn.one_hot(s.agent_pos[i, 0], self.env.height),
                                       jax.nn.one_hot(s.agent_pos[i, 1], self.env.width)])
                      for i in range(self.n_agents)]
        if self.own_termination:
            parts.append(jax.nn.one_hot(s.running + 1, self.options.n + 1).ravel())
        return jnp.concatenate(parts)

    def config_of(self, s: EnvState) -> jax.Array:
        """int32: the bitmask of the rubble groups cleared in ``s`` (0 without rubble)."""
        return self.rubble.config_of(self.rubble.mode_of(s.rubble)) if self.n_groups else jnp.zeros((), jnp.int32)

    def decode(self, obs: jax.Array):
        """(regions int[n_agents], flags bool[F] (``flags``), config int32) of an abstract state."""
        n, v = self.n_agents * self.n_regions, self.n_flags
        regions = jnp.argmax(obs[:n].reshape(self.n_agents, self.n_regions), -1)
        cleared = obs[n + v: n + v + self.n_groups] > 0.5
        config = jnp.sum(cleared.astype(jnp.int32) << jnp.arange(self.n_groups, dtype=jnp.int32))
        return regions, obs[n: n + v] > 0.5, config

    def running_of(self, obs: jax.Array) -> jax.Array:
        """int32[n_agents]: each medic's running option in an abstract state (-1: none)."""
        if not self.own_termination:
            return jnp.full(self.n_agents, -1, jnp.int32)
        width = self.n_agents * (self.options.n + 1)
        return jnp.argmax(obs[-width:].reshape(self.n_agents, -1), -1).astype(jnp.int32) - 1

    def available(self, regions: jax.Array, triaged: jax.Array, config: jax.Array = 0) -> jax.Array:
        """bool[n_agents, O]: options each agent may start (initiation set met for its role, and a
        sub-policy exists)."""
        can = jax.vmap(self.options.can_initiate, in_axes=(0, None, None, 0))(regions, triaged, config,
                                                                              jnp.asarray(self.env.roles))
        return can & (jnp.asarray(self.policy_for)[jnp.arange(self.n_agents), regions] >= 0)

    def valid_options(self, obs: jax.Array) -> jax.Array:
        """bool[n_agents, O]: each agent's valid part of a joint option: an available option, or any
        option for an idle agent (one with none available; its part is ignored)."""
        avail = self.available(*self.decode(obs))
        running = self.running_of(obs)
        own = jnp.arange(self.options.n) == running[:, None]  # a busy medic's only valid choice
        return jnp.where(running[:, None] >= 0, own, avail | ~avail.any(-1, keepdims=True))

    def valid_joint(self, obs: jax.Array) -> jax.Array:
        """bool[n_joint]: joint options whose every agent's part is valid (flat coordinator only)."""
        ok = self.valid_options(obs)[jnp.arange(self.n_agents), jnp.asarray(self.joint)]  # [n_joint, n_agents]
        return ok.all(-1)

    # -- dynamics ----------------------------------------------------------------------------------
    def reset(self, key, p: CoordinatorParams | None = None):
        _, s = self.env.reset(key)
        s = self.wrap(s)
        return self.observe(s), s

    def wrap(self, s: EnvState) -> MacroState:
        """A team env state with no option running."""
        none = jnp.full(self.n_agents, -1, jnp.int32)
        return MacroState(env=s, running=none, elapsed=jnp.zeros(self.n_agents, jnp.int32))

    def primitive_actions(self, s: EnvState, options: jax.Array, active: jax.Array, p: CoordinatorParams):
        """int32[n_agents]: each active agent's sub-policy action for its option; TRIAGE for idle ones."""
        acts, done = [], self.slot_done(s)
        regions = jnp.zeros(self.n_agents, jnp.int32) if self.region_invariant else \
            self.env.graph.region_of(s.agent_pos)
        for i in range(self.n_agents):
            o = options[i]
            task = jnp.asarray(self.policy_for)[i, regions[i], o]
            victim = jnp.asarray(self.options.victim)[o]
            goal = jnp.asarray(self.option_goals)[o]
            if self.drawn:  # TRIAGE-IN-R: its room's task, told the slot it works on
                slot = self.target_slot(s, i, victim, done)
                triage = jnp.asarray(self.options.kind)[o] == OPTION_TRIAGE
                task, goal = (jnp.where(triage, jnp.asarray(a)[slot], b) for a, b in ((self.slot_task, task),
                                                                                      (self.slot_goal, goal)))
                victim = jnp.where(triage, slot, -1)
            params = jax.tree.map(lambda x: x[jnp.maximum(task, 0)], p.subpolicy)
            flag = jnp.where(victim >= 0, done[jnp.maximum(victim, 0)], False)
            if self.n_groups:  # the sub-policy's index: goal x modes + which rubble cells are cleared
                mode = self.rubble.mode_of(s.rubble)
                if self.drawn:  # a TRIAGE-IN-R task no rubble matters to runs in mode 0
                    mode = jnp.where(triage & ~jnp.asarray(self.slot_every_mode)[slot], 0, mode)
                goal = goal * self.rubble.n_modes + mode
            a = self.subpolicy_act(params, self.observe_agent(s.agent_pos[i], s.agent_dir[i], flag, goal))[0]
            acts.append(jnp.where(active[i], a, TRIAGE))
        return jnp.stack(acts).astype(jnp.int32)

    def terminated(self, s: EnvState, options: jax.Array, active: jax.Array) -> jax.Array:
        """bool[n_agents]: the active medics whose options have reached their termination condition in ``s``."""
        done = jax.vmap(self.options.terminated, in_axes=(0, 0, None, None))
        return active & done(options, self.env.graph.region_of(s.agent_pos), self.flags(s), self.config_of(s))

    def unblocked(self) -> jax.Array:
        """int32[2, n_agents]: ``advance``'s blocked counts and dodge phases at a decision's start."""
        return jnp.zeros((2, self.n_agents), jnp.int32)

    def advance(self, s: EnvState, options: jax.Array, active: jax.Array, blocked: jax.Array,
                p: CoordinatorParams):
        """One primitive step of a running joint option: (state, team reward, done, blocked), where
        ``blocked`` int32[2, n_agents] holds how often each agent has been stopped by another since it
        last moved, and its ``dodge`` phase (2: turn right next, 1: then forward)."""
        count, phase = blocked
        acts = self.primitive_actions(s, options, active, p)
        if self.dodge:
            acts = jnp.where(phase == 2, TURN_RIGHT, jnp.where(phase == 1, FORWARD, acts))
        _, st, r, done, _ = self.env.step(None, s, acts)
        if not (self.block_patience or self.dodge):  # nothing reads the counts
            return st, r, done, blocked
        front = st.agent_pos + jnp.asarray(DIR_DELTA)[st.agent_dir]
        held = jnp.all(front[:, None] == st.agent_pos[None], -1) & ~jnp.eye(self.n_agents, dtype=bool)
        stopped = active & (acts == FORWARD) & jnp.all(st.agent_pos == s.agent_pos, -1) & held.any(-1)
        moved = jnp.any(st.agent_pos != s.agent_pos, -1)
        count = jnp.where(stopped, count + 1, jnp.where(moved, 0, count))
        if self.dodge:
            phase = jnp.where(stopped & (phase == 0), 2, jnp.maximum(phase - 1, 0))
        return st, r, done, jnp.stack([count, phase])

    def ended(self, s: EnvState, options: jax.Array, active: jax.Array, blocked: jax.Array,
              elapsed: jax.Array) -> jax.Array:
        """bool[n_agents]: the medics whose options end in ``s`` after ``elapsed`` steps each: their
        termination condition, the timeout, or (``block_patience``) blocked that long."""
        over = self.terminated(s, options, active) | (elapsed >= self.option_timeout)
        return over | (blocked[0] >= self.block_patience) if self.block_patience else over

    def option_over(self, s: EnvState, options: jax.Array, active: jax.Array, blocked: jax.Array,
                    elapsed: jax.Array) -> jax.Array:
        """bool: the decision's options run no further: some medic's option ended (``ended``)."""
        return jnp.any(self.ended(s, options, active, blocked, elapsed))

    def still_running(self, s: MacroState, st: EnvState, options: jax.Array, active: jax.Array,
                      blocked: jax.Array, k: jax.Array):
        """(running, elapsed) int32[n_agents] after a decision's ``k`` steps from ``s`` to ``st``: with
        ``own_termination`` the options that did not end run on; else none does."""
        if not self.own_termination:
            return s.running, s.elapsed
        over = self.ended(st, options, active, blocked, s.elapsed + k) | ~active
        return jnp.where(over, -1, options), jnp.where(over, 0, s.elapsed + k)

    def step(self, key, s: MacroState | EnvState, action: jax.Array, p: CoordinatorParams):
        s = self.wrap(s) if isinstance(s, EnvState) else s
        options = self.options_of(action)
        obs = self.observe(s)
        active = self.available(*self.decode(obs)).any(-1)  # non-idle agents
        valid = self.valid_options(obs)[jnp.arange(self.n_agents), options].all()
        elapsed = s.elapsed  # zeros under the paper's rule

        def body(c):
            st, ret, disc, k, done, blocked = c
            st, r, done, blocked = self.advance(st, options, active, blocked, p)
            return st, ret + r, disc + self.gamma ** k * r, k + 1, done, blocked

        def cond(c):
            st, _, _, k, done, blocked = c
            return ~done & ~self.option_over(st, options, active, blocked, elapsed + k)

        zero = jnp.zeros((), jnp.float32)

        def run(st):
            # under vmap this cond becomes a select that computes both branches: ``done`` starts as
            # ``~valid`` so an invalid lane's loop runs no step (it would run a wrong sub-policy up to the
            # timeout, and the batch would wait on it; its result is dropped either way)
            st, ret, disc, k, _, blocked = jax.lax.while_loop(
                cond, body, (st, zero, zero, jnp.zeros((), jnp.int32), ~valid, self.unblocked()))
            return (st, ret, disc, k) + self.still_running(s, st, options, active, blocked, k)

        # an invalid choice: penalty, one step of standing still
        stand = lambda st: (st.replace(t=st.t + 1), jnp.float32(self.invalid_penalty),
                            jnp.float32(self.invalid_penalty), jnp.ones((), jnp.int32), s.running, s.elapsed)
        st, ret, disc, k, running, elapsed = jax.lax.cond(valid, run, stand, s.env)
        s = MacroState(env=st, running=running, elapsed=elapsed)
        terminated = jnp.all(st.triaged) if self.plain else jnp.all(st.triaged | st.dead)
        done = terminated | (st.t >= self.horizon)
        info = {"terminated": terminated, "steps": k, "discounted_reward": disc, "valid": valid}
        return self.observe(s), s, ret, done, info


def coordinator_dqn(cfg: CoordinatorConfig) -> DQNConfig:
    return DQNConfig(hidden=cfg.hidden, lr=cfg.lr, gamma=cfg.gamma, batch_size=cfg.batch_size,
                     buffer_capacity=cfg.buffer_capacity, learning_starts=cfg.learning_starts, train_every=1,
                     gradient_steps=cfg.gradient_steps, n_step=cfg.n_step, reward_scale=cfg.reward_scale,
                     target_update_every=cfg.target_update_every, eps_start=cfg.eps_start, eps_end=cfg.eps_end,
                     eps_decay_steps=cfg.eps_decay_steps, double_dqn=False)


def make_learner(macro: MacroEnv, cfg: CoordinatorConfig) -> IndependentDQN | FactoredDQN:
    """``cfg.kind``: ``flat`` (the paper): a single DQN over the joint options; ``factored``: one option
    head per medic, their values summed (``FactoredDQN``), each medic's choice masked to its valid
    options. Both learn from the SMDP target (Sutton et al. 1999, eq. 8)."""

    def row(transition):
        info = transition["info"]
        row = default_row(transition)
        return {**row, "reward": info["discounted_reward"], "gamma": cfg.gamma ** info["steps"].astype(jnp.float32),
                "terminal": row["terminal"] | ~info["valid"]}  # an invalid choice is a dead end

    dqn = coordinator_dqn(cfg)
    if cfg.kind == "factored":
        return FactoredDQN(macro.obs_dim, macro.options.n, macro.n_agents, dqn, macro.valid_options, row_fn=row,
                           obs_blocks=macro.obs_blocks)
    return IndependentDQN(macro.obs_dim, macro.n_joint, 1, dqn, dqn_target(dqn, macro.valid_joint), row_fn=row,
                          valid_fn=macro.valid_joint, mask_greedy=False, obs_blocks=macro.obs_blocks)
