"""Typed, frozen experiment configs loaded from YAML and validated before anything compiles.

A config file has up to four sections, each a frozen dataclass below::

    algo: iql                 # which learner (jaxusar/algos/<algo>.py)
    env:   {map: two_rooms, horizon: 300, ...}
    dqn:   {hidden: [64, 64], lr: 0.0005, ...}
    train: {episodes: 5000, test_every: 50, ...}
    seed: 0

Unknown keys, wrong types and impossible values raise ``ConfigError`` naming the dotted key.
``--set train.episodes=200`` style overrides go through the same validation. Layers, each over the one
before: the dataclass defaults, an algorithm's ``DEFAULTS``, the defaults derived from the map
(``map_defaults``: the coordinator kind, option termination and budgets from its size), the map's
``NAME.settings.yaml`` (settings
that name its tasks or regions, or that one learner needs there, so they apply only on that map; see
``map_settings``), a config file, ``--set``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import types
import typing
from pathlib import Path
from typing import Any

import yaml


class ConfigError(ValueError):
    """A config that cannot be run; the message names the offending key."""


OPTION_KINDS = ("navigate", "triage", "clear", "search")  # the option kinds hierarchical.option_kinds may name


def _without_added_defaults(obj, d: dict) -> dict:
    """``d`` (``dataclasses.asdict(obj)``) without the ``added`` fields (``_field``) at their defaults."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            _without_added_defaults(value, d[f.name])
        elif f.metadata.get("added") and value == f.default:
            del d[f.name]
    return d


def _field(default, check=None, doc="", added=False):
    """A config field: its default, a check of a value, and its help text. ``added``: a field that came
    after results were committed; ``to_dict`` leaves it out at its default, so their configs hash as before."""
    meta = {"check": check, "doc": doc, "added": added}
    if isinstance(default, dict):  # mutable: each config gets its own copy
        return dataclasses.field(default_factory=lambda: dict(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _positive(x):
    return x > 0


def _non_negative(x):
    return x >= 0


def _unit_interval(x):
    return 0 <= x <= 1


def _map_setting(key: str):
    """The check of env setting ``key``: the env's own (``envs.layout.header_value``); None (the map's own) passes."""

    def check(value) -> bool:
        if value is None:
            return True
        from jaxusar.envs.layout import LayoutError, header_value  # config stays importable without jax

        try:
            header_value(key, value, "env")
        except LayoutError:
            return False
        return True

    return check


# The map settings a layout's header may set (``jaxusar.envs.HEADER_KEYS``): None = the map's own.
MAP_SETTINGS = ("random_victims", "triage_steps", "critical_triage_steps", "critical_reward", "critical_expires",
                "view_radius", "observation")


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """The env: ``envs.make(map, **overrides())``. The episode settings always apply; the map settings
    (``MAP_SETTINGS``) are None unless set, and the map's header (else the contract default) then decides."""

    map: str = _field("two_rooms", doc="shipped map name or path to a .txt layout")
    horizon: int = _field(300, _positive, "episode cap; the paper's figures use 300")
    triage_reward: float = _field(100.0, doc="team reward per newly triaged victim")
    step_penalty: float = _field(0.0, doc="team reward added every step")
    start_dir: str = _field("NORTH", lambda s: s.upper() in ("EAST", "SOUTH", "WEST", "NORTH"), "EAST/SOUTH/WEST/NORTH")
    random_victims: tuple[int, ...] | None = _field(None, _map_setting("random_victims"),
                                                    "[N_REGULAR, N_CRITICAL] victims drawn at reset on the '?' cells")
    triage_steps: int | None = _field(None, _map_setting("triage_steps"), "TRIAGE actions a regular victim needs, >= 1")
    critical_triage_steps: int | None = _field(None, _map_setting("critical_triage_steps"),
                                               "TRIAGE actions a critical victim needs, >= 1")
    critical_reward: float | None = _field(None, _map_setting("critical_reward"), "team reward per critical victim")
    critical_expires: int | str | None = _field(None, _map_setting("critical_expires"),
                                                "step at which untriaged critical victims die, >= 1, or none")
    view_radius: int | str | None = _field(None, _map_setting("view_radius"),
                                           "Chebyshev radius an agent sees within its region, >= 0, or none")
    observation: str | None = _field(None, _map_setting("observation"),
                                     "full (the state) or view (each agent its own partial observation)")

    def overrides(self) -> dict:
        """The ``envs.make`` overrides: the episode settings and every map setting that is set."""
        out = {k: getattr(self, k) for k in ("horizon", "triage_reward", "step_penalty", "start_dir")}
        return out | {k: getattr(self, k) for k in MAP_SETTINGS if getattr(self, k) is not None}


@dataclasses.dataclass(frozen=True)
class DQNConfig:
    hidden: tuple[int, ...] = _field((32, 32), lambda h: len(h) > 0 and all(w > 0 for w in h), "MLP widths")
    lr: float = _field(5e-4, _positive, "Adam learning rate, > 0")
    lr_schedule: str = _field("constant", lambda s: s in ("constant", "linear", "cosine"),
                              "constant, linear or cosine decay from lr to lr_end over lr_decay_updates")
    lr_end: float = _field(5e-5, _positive, "final learning rate of a decaying lr_schedule, in (0, lr]")
    lr_decay_updates: int = _field(20_000, _positive, "gradient updates of the lr decay, >= 1")
    gamma: float = _field(0.99, lambda g: 0 < g <= 1, "discount, in (0, 1]")
    batch_size: int = _field(32, _positive)
    buffer_capacity: int = _field(50_000, _positive, "replay rows per learner")
    learning_starts: int = _field(1_000, _non_negative, "env steps before the first update")
    train_every: int = _field(8, _positive, "env steps between learning steps, >= 1")
    gradient_steps: int = _field(1, _positive, "gradient updates per learning step, >= 1 (replay ratio = "
                                 "gradient_steps / train_every updates per env step)")
    n_step: int = _field(1, _positive, "steps of the return before bootstrapping, >= 1 (cut at episode ends)")
    n_step_cut_exploring: bool = _field(False, doc="n-step returns also stop before an exploring action "
                                        "(Watkins's cut: they then estimate Q*, not the exploring policy's Q)")
    n_step_cut_greedy: bool = _field(False, doc="n-step returns stop before a stored action that is not the "
                                     "current target net's argmax over all actions (Watkins's cut at update "
                                     "time: old exploring data stop too)")
    reward_scale: float = _field(1.0, _positive, "> 0: rewards are multiplied by this before learning (Q is "
                                 "learned in scaled units; the greedy policy is unchanged)")
    target_update_every: int = _field(250, _positive, "updates between hard target copies (if tau == 1)")
    tau: float = _field(1.0, lambda t: 0 < t <= 1, "in (0, 1]: 1 = hard copy every target_update_every; "
                        "< 1 = Polyak averaging each update")
    double_dqn: bool = _field(False)
    one_hot_input: bool = _field(False, doc="the first layer looks up its weight rows at the observation's one-hot "
                                 "blocks instead of multiplying the whole vector: the same network, a cost per block "
                                 "instead of per feature (maps with wide cell inputs); float sums may round "
                                 "differently, so off by default")
    loss: str = _field("huber", lambda s: s in ("huber", "mse"), "huber or mse")
    max_grad_norm: float = _field(10.0, _positive)
    eps_start: float = _field(1.0, _unit_interval)
    eps_end: float = _field(0.05, _unit_interval)
    eps_decay_steps: int = _field(50_000, _positive, "env steps of the linear epsilon decay")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    episodes: int = _field(5000, _positive, "training episodes per trial")
    test_every: int = _field(50, _positive, "a greedy test episode every this many training episodes")
    chunk_steps: int = _field(20_000, _positive, "env steps per jitted chunk (progress and checkpoints between chunks)")
    optimal_slack: int = _field(0, _non_negative, "a test is optimal within planner optimum + this many steps")
    stop_at_optimal: bool = _field(False, doc="a trial stops once a test was optimal (its episodes to optimal and "
                                   "kept params are those of the full budget; its curves end at the chunk "
                                   "where that test ran)")
    test_draws: int = _field(1, _positive, "greedy episodes per test, each from its own reset key, the same keys at "
                             "every test of a trial (return and steps: their means; solved: all of them); where "
                             "victims are drawn the map-derived default is 8, so that the kept params are the best "
                             "on the same draws, not on the easiest draw", added=True)
    drop_finished: bool = _field(True, doc="between chunks, run only the trials still short of their episodes "
                                 "once they fit a smaller batch (compiled once per batch size); false steps every "
                                 "trial to the end (the benchmark's --quick: there a smaller batch's compiling "
                                 "costs more than its chunks save)", added=True)


@dataclasses.dataclass(frozen=True)
class DOCConfig:
    """Simplified distributed option-critic (algos/option_critic.py); its critic uses the dqn section."""

    options: tuple[int, ...] = _field((2, 4, 8), lambda ks: len(ks) > 0 and all(k >= 1 for k in ks),
                                      "options per agent, one run each (paper Fig. 5: 2, 4, 8)")
    actor_hidden: tuple[int, ...] = _field((32, 32), lambda h: len(h) > 0 and all(w > 0 for w in h),
                                           "per-agent actor MLP widths (intra-option policies + terminations)")
    actor_lr: float = _field(5e-4, _positive, "actor Adam learning rate")
    entropy_weight: float = _field(0.01, _non_negative, "entropy bonus of the intra-option policies")
    xi: float = _field(0.01, doc="termination regularizer added to the termination advantage (Bacon et al.)")
    value_baseline: str = _field("max", lambda s: s in ("max", "mean"),
                                 "V in the termination advantage: max or mean over the agent's options")
    termination_at: str = _field("next", lambda s: s in ("next", "current"),
                                 "termination gradient at s' (next; Bacon et al.) or at s (current)")
    actor_data: str = _field("recent", lambda s: s in ("recent", "replay"),
                             "actor batch: the train_every newest transitions (recent) or the critic's replay batch")
    greedy_termination: float = _field(0.5, _unit_interval, "a greedy test ends an option where beta >= this")


@dataclasses.dataclass(frozen=True)
class CoordinatorConfig:
    """The SMDP coordinator over joint options (paper Sec. IV-C)."""

    kind: str = _field("flat", lambda s: s in ("flat", "factored"),
                       "flat (the paper: one Q-value per joint option, options ^ medics of them) or factored (one "
                       "option head per medic, values summed: linear in the medics)")
    max_joint_options: int = _field(4096, _positive, "the flat coordinator refuses a map with more joint options")
    episodes: int = _field(100, _positive, "coordinator training episodes per trial")
    test_every: int = _field(1, _positive, "a greedy team test every this many coordinator episodes")
    invalid_penalty: float = _field(-100.0, doc="reward for a joint option whose initiation set is not met")
    option_timeout: int = _field(0, _non_negative, "an option running this many primitive steps terminates; 0: "
                                 "1.5x the longest optimal path of any option, at least 50 (two_rooms: 50)")
    block_patience: int = _field(0, _non_negative, "the options also end once an agent has been stopped this "
                                 "many times by another without moving; 0: off (the paper's options)")
    dodge: bool = _field(False, doc="an agent blocked by another steps aside (turn right, forward) before its "
                         "sub-policy acts again; on by default where rubble lies (agents wait beside it)", added=True)
    termination: str = _field("all", lambda s: s in ("all", "own"),
                              "all (the paper: every medic's option ends when the first one does, and the "
                              "coordinator chooses for all) or own (each option runs to its own end; the "
                              "coordinator chooses only for the medics whose options ended)")
    features: str = _field("regions", lambda s: s in ("regions", "cells"),
                           "the coordinator's input: each medic's region and the triaged flags (regions, the "
                           "paper's graph view), or the same plus each medic's row and column (cells)")
    hidden: tuple[int, ...] = _field((32,), lambda h: len(h) > 0 and all(w > 0 for w in h), "MLP widths")
    lr: float = _field(5e-3, _positive)
    gamma: float = _field(0.95, lambda g: 0 < g <= 1,
                          "discount per primitive step (gamma^k per option); 0.95, not 0.99: 18 vs 19 team steps "
                          "must differ in value by more than the fit's noise")
    batch_size: int = _field(16, _positive)
    buffer_capacity: int = _field(2_000, _positive)
    learning_starts: int = _field(16, _non_negative, "decisions before the first update")
    target_update_every: int = _field(20, _positive)
    gradient_steps: int = _field(8, _positive, "gradient updates per decision, >= 1 (8: chosen over exact "
                                 "sub-policies on tuning seeds, benchmarks/README.md)")
    n_step: int = _field(1, _positive, "decisions (options) of the return before bootstrapping, >= 1")
    reward_scale: float = _field(0.01, _positive, "> 0: rewards are multiplied by this before learning (0.01: "
                                 "the +100 triage rewards become 1)")
    eps_start: float = _field(1.0, _unit_interval)
    eps_end: float = _field(0.05, _unit_interval)
    eps_decay_steps: int = _field(200, _positive, "decisions of the linear epsilon decay")
    chunk_steps: int = _field(64, _positive, "decisions per jitted chunk")
    stop_at_optimal: bool = _field(True, doc="a trial stops once a team test was optimal, as train.stop_at_optimal "
                                   "(its episodes to optimal and kept params are those of the full budget)")


@dataclasses.dataclass(frozen=True)
class HierarchicalConfig:
    """The paper's method: option sub-policies (DQN on pseudo-rewards) + the coordinator.

    The sub-policies use the top-level ``dqn`` and ``train`` sections (train.test_every: paper 10).
    """

    task_gamma: dict[str, float] = _field(
        {}, lambda d: all(0 < g <= 1 for g in d.values()),
        "per-task discount overriding dqn.gamma, by task name (two_rooms sets TRIAGE-BOTTOM-VICTIM: 0.9 in its "
        "settings file, paper Fig. 4f)")
    triage_start: str = _field("room", lambda s: s in ("room", "entry"),
                               "triage tasks start anywhere in the room, or at its entry cells")
    subpolicy_features: str = _field("factored", lambda s: s in ("factored", "cell"),
                                     "a sub-policy's input: one-hot row, col and facing (factored), or the "
                                     "same plus a one-hot of the cell (cell)")
    navigate_start: str = _field("mixed", lambda s: s in ("mixed", "initiation"),
                                 "navigation tasks start half at the medic's start and half anywhere in the "
                                 "initiation set (mixed), or anywhere in it (initiation)")
    focus_starts: float = _field(0.5, _unit_interval,
                                 "the fraction of sub-policy training episodes, in [0, 1], that start at an "
                                 "initiation state from which the latest test's greedy policy was not optimal, while "
                                 "there is one (0: every start as navigate_start and triage_start say; 0.5: chosen on "
                                 "tuning seed 1000, benchmarks/README.md)")
    navigation: str = _field("chained", lambda s: s in ("adjacent", "chained", "goal"),
                             "adjacent (the paper: a sub-policy per medic and room next to its start region), "
                             "chained (a sub-policy per region, shared by the medics; NAVIGATE to any room chains "
                             "them along the region graph's shortest path) or goal (one sub-policy for every room, "
                             "shared by the medics, told the room in its input)")
    option_kinds: tuple[str, ...] = _field(
        (), lambda k: all(x in OPTION_KINDS for x in k) and len(set(k)) == len(k),
        "the option kinds to build, e.g. [navigate, triage] (navigate, triage, clear: engineers' rubble "
        "clearing; search: refused, under view TRIAGE-IN-R searches); empty: every kind the map offers",
        added=True)
    coordinator: CoordinatorConfig = dataclasses.field(default_factory=CoordinatorConfig)


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
    algo: str = _field("iql", doc="learner name")
    seed: int = _field(0, _non_negative)
    env: EnvConfig = dataclasses.field(default_factory=EnvConfig)
    dqn: DQNConfig = dataclasses.field(default_factory=DQNConfig)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)
    doc: DOCConfig = dataclasses.field(default_factory=DOCConfig)
    hierarchical: HierarchicalConfig = dataclasses.field(default_factory=HierarchicalConfig)

    def to_dict(self) -> dict:
        """The config as a dict; map settings left to the map are left out, so a config that sets none
        reads (and hashes) as it did before they existed."""
        out = _without_added_defaults(self, dataclasses.asdict(self))
        out["env"] = {k: v for k, v in out["env"].items() if k not in MAP_SETTINGS or v is not None}
        return out

    def hash(self) -> str:
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()[:12]

    def validate(self) -> "ExperimentConfig":
        """Checks that span several fields."""
        d, t = self.dqn, self.train
        if d.buffer_capacity < d.batch_size:
            raise ConfigError(f"dqn.buffer_capacity={d.buffer_capacity} is smaller than dqn.batch_size={d.batch_size}")
        if d.eps_end > d.eps_start:
            raise ConfigError(f"dqn.eps_end={d.eps_end} is above dqn.eps_start={d.eps_start}")
        if d.n_step_cut_exploring and d.n_step_cut_greedy:
            raise ConfigError("dqn.n_step_cut_exploring and dqn.n_step_cut_greedy are both true: choose one cut "
                              "(the acting params' greedy action, or the current target net's)")
        if d.lr_schedule != "constant" and d.lr_end > d.lr:
            raise ConfigError(f"dqn.lr_end={d.lr_end} is above dqn.lr={d.lr}: a decaying lr_schedule needs "
                              "lr_end in (0, lr]")
        if t.test_every > t.episodes:
            raise ConfigError(f"train.test_every={t.test_every} exceeds train.episodes={t.episodes}: no test would run")
        c = self.hierarchical.coordinator
        if self.algo == "hierarchical" and c.test_every > c.episodes:
            raise ConfigError(f"hierarchical.coordinator.test_every={c.test_every} exceeds hierarchical.coordinator."
                              f"episodes={c.episodes}: no team test would run")
        if t.chunk_steps < d.train_every:
            raise ConfigError(f"train.chunk_steps={t.chunk_steps} is below dqn.train_every={d.train_every}")
        check_map_path(self.env.map, "env.map: ")
        return self


def check_map_path(name: str, prefix: str = "") -> None:
    """A map given as a path (it ends in .txt or holds a folder) must be a .txt file that exists: say so,
    rather than call it an unknown map name. Shipped map names pass."""
    path = Path(name)
    if path.suffix != ".txt" and len(path.parts) < 2:
        return  # a name: shipped or not, the env's error lists the shipped ones
    if not path.exists():
        raise ConfigError(f"{prefix}the map file {name!r} does not exist")
    if not path.is_file() or path.suffix != ".txt":
        raise ConfigError(f"{prefix}{name!r} is not a .txt layout file")


def _coerce(value: Any, tp: Any, key: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):  # the first type that takes the value (None: only as null)
        arms = typing.get_args(tp)
        if value is None and type(None) in arms:
            return None
        for arm in (a for a in arms if a is not type(None)):
            try:
                return _coerce(value, arm, key)
            except ConfigError:
                pass
        names = " or ".join("null" if a is type(None) else getattr(a, "__name__", str(a)) for a in arms)
        raise ConfigError(f"{key}: expected {names}, got {value!r}")
    if origin is dict:
        kt, vt = typing.get_args(tp)
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a mapping, got {value!r}")
        return {_coerce(k, kt, f"{key} key"): _coerce(v, vt, f"{key}.{k}") for k, v in value.items()}
    if origin is tuple:
        (elem, _) = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        return tuple(_coerce(v, elem, f"{key}[{i}]") for i, v in enumerate(value))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true/false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    raise ConfigError(f"{key}: unsupported type {tp}")  # pragma: no cover


def from_dict(cls, data: dict, prefix: str = ""):
    """Build a (nested) config dataclass from a dict, validating every key."""
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix.rstrip('.') or 'config'}: expected a mapping, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"unknown key {prefix + unknown[0]!r}; allowed under {prefix.rstrip('.') or 'top level'}: {sorted(fields)}")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        key, tp = prefix + name, hints[name]
        if dataclasses.is_dataclass(tp):
            kwargs[name] = from_dict(tp, value, key + ".")
            continue
        value = _coerce(value, tp, key)
        check = fields[name].metadata.get("check")
        if check is not None and not check(value):
            doc = fields[name].metadata.get("doc")
            raise ConfigError(f"{key}={value!r} is out of range" + (f" ({doc})" if doc else ""))
        kwargs[name] = value
    return cls(**kwargs)


def parse_set(items: list[str]) -> dict:
    """``["train.episodes=200", "dqn.hidden=[32,32]"]`` -> nested dict (values parsed as YAML)."""
    out: dict = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected key=value, e.g. train.episodes=200")
        key, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError as e:
            raise ConfigError(f"--set {key}: cannot parse value {raw!r}: {e}") from None
        node = out
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {key}: {part!r} is not a section")
        node[parts[-1]] = value
    return out


def _merge(base: dict, extra: dict) -> dict:
    """``extra`` over ``base``, mapping by mapping; an empty mapping in ``extra`` clears (``task_gamma={}``)."""
    out = dict(base)
    for k, v in extra.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and v and isinstance(out.get(k), dict) else v
    return out


def _read_yaml(path: Path, what: str) -> dict:
    try:
        loaded = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"{what} {str(path)!r} is not valid YAML: {e}") from None
    if not isinstance(loaded, dict):
        raise ConfigError(f"{what} {str(path)!r}: expected a mapping at the top level")
    return loaded


def map_settings(data: dict) -> dict:
    """The settings file of the map that ``data`` (a config dict) runs on, or {} (envs/layout.py): its
    sections for every algorithm, then its ``algorithms.<algo>`` section for ``data``'s algorithm only
    (a budget one learner needs on this map, say)."""
    from jaxusar.envs.layout import settings_path

    env = data.get("env", {})
    name = env.get("map", EnvConfig.map) if isinstance(env, dict) else None
    path = settings_path(name) if isinstance(name, str) else None
    if path is None:
        return {}
    settings = _read_yaml(path, "map settings file")
    own = settings.pop("algorithms", None) or {}
    try:
        if not isinstance(own, dict):
            raise ConfigError("algorithms: expected a mapping of algorithm names to settings")
        from jaxusar import algos

        for algo, part in own.items():
            algos.algorithm(algo)  # an unknown name: a ConfigError listing the known ones
            if not isinstance(part, dict):
                raise ConfigError(f"algorithms.{algo}: expected a mapping of settings")
            from_dict(ExperimentConfig, _merge(settings, part))
        from_dict(ExperimentConfig, settings)
    except ConfigError as err:
        raise ConfigError(f"map settings file {str(path)!r}: {err}") from None
    return _merge(settings, own.get(data.get("algo", ExperimentConfig.algo)) or {})


# The map-derived defaults (``map_defaults``): the settings office's and four_rooms' tuning found, as rules
# on what any map has, so that a map with no settings file gets them too (benchmarks/README.md, "The flat
# and factored coordinators" and "Long corridors cut into pieces").
FACTORED_FROM_AGENTS = 3   # the flat head is options ^ agents wide: from three agents the factored one wins
OWN_END_FROM_AGENTS = 4    # from four agents an option ending every few steps re-routes the whole team
WIDE_MAP_CELLS = 512       # a cell one-hot this wide: look its weight rows up; the sub-policy lanes are many
# where victims are drawn: many draws to learn over (tuned on minimap, seeds 1000-1001, over exact sub-policies)
DRAWN_COORDINATOR = {"episodes": 1500, "eps_decay_steps": 3000, "test_every": 5, "gamma": 0.99, "n_step": 3}


def map_defaults(data: dict) -> dict:
    """Settings derived from the map that ``data`` (a config dict) runs on: a layer over the algorithm's
    defaults and under the map's settings file, a config file and ``--set``.

    - from 3 agents, the factored coordinator (one option head per agent);
    - from 4 agents, and where rubble lies, options that run to their own end, with a coordinator budget
      three times the default and epsilon decayed over three times as many decisions (300 and 600:
      office's tuning, seed 1000); where rubble lies five times (500 and 1,000): an engineer's CLEAR and
      the medics' walks end far apart, and clearing pays only decisions later (two_rooms_rubble over exact
      sub-policies: own termination 2/8 -> 8/8 trials at the optimum at seed 1000; x3 -> x5 30/32 -> 32/32
      at seeds 1000-4000; benchmarks/README.md, "The paper's method on rubble");
    - where rubble lies, blocked agents step aside (``dodge``): waiting beside rubble, agents stand in
      others' way;
    - where victims are drawn, tests of 8 draws (``train.test_draws``), and for the paper's method a
      coordinator budget of 1,500 episodes, epsilon decayed over 3,000 decisions, a test every 5 episodes,
      a discount of 0.99 a step and returns over 3 decisions (``DRAWN_COORDINATOR``; minimap over exact
      sub-policies, seed 1000: normalized score median 0.70 at 500 episodes, 0.73 at 1,500; under "view"
      0.72, worst trial 0.59, at gamma 0.95, and 0.74, worst 0.72, at 0.99: episodes run to the horizon, and
      at 0.95 a victim 50 steps off is worth 0.08 of one at hand; 3-decision returns: 0.76, worst 0.72, at
      seed 1000 and 0.75, worst 0.69, at seed 1001, against one decision's 0.74 and 0.68, worst 0.65;
      with trained sub-policies at seed 1000, 0.76, worst 0.69, against 0.72, worst 0.68;
      benchmarks/README.md, "The paper's method on drawn victims". On the reporting seed 0 with trained
      sub-policies they did not carry, 0.71 against 0.74: results/minimap/README.md);
    - on a map of 512 cells or more, the sub-policies' one-hot input looked up, and for the paper's
      method shorter sub-policy chunks (1,000 steps) with an update every 2 env steps.

    {} for a map that does not load: its error comes later, from the env, with its own message."""
    from jaxusar.envs.layout import LayoutError, load_layout

    env = data.get("env", {})
    name = env.get("map", EnvConfig.map) if isinstance(env, dict) else None
    try:
        layout = load_layout(name)
    except (LayoutError, OSError, TypeError, ValueError):
        return {}
    agents = len(layout.agent_start)
    out: dict = {}
    coordinator = {}
    if agents >= FACTORED_FROM_AGENTS:
        coordinator["kind"] = "factored"
    if agents >= OWN_END_FROM_AGENTS or layout.rubble.any():
        default, scale = CoordinatorConfig(), 5 if layout.rubble.any() else 3
        coordinator.update(termination="own", episodes=scale * default.episodes,
                           eps_decay_steps=scale * default.eps_decay_steps)
    if layout.rubble.any():
        coordinator["dodge"] = True
    if coordinator:
        out["hierarchical"] = {"coordinator": coordinator}
    if len(layout.random_cells):
        out = _merge(out, {"train": {"test_draws": 8}})
        if data.get("algo", ExperimentConfig.algo) == "hierarchical":
            out = _merge(out, {"hierarchical": {"coordinator": DRAWN_COORDINATOR}})
    if layout.shape[0] * layout.shape[1] >= WIDE_MAP_CELLS:
        out["dqn"] = {"one_hot_input": True}
        if data.get("algo", ExperimentConfig.algo) == "hierarchical":
            out = _merge(out, {"train": {"chunk_steps": 1000}, "dqn": {"train_every": 2}})
    return out


def load(path: str | Path | None = None, sets: list[str] | None = None, defaults: dict | None = None,
         cls=ExperimentConfig):
    """The config of ``defaults``, then the map's settings file (if any), then the YAML file at ``path``,
    then ``--set`` overrides; validated and frozen. Each layer overrides the ones before it."""
    loaded = {}
    if path is not None:
        path = Path(path)
        if not path.exists():
            raise ConfigError(f"config file {str(path)!r} does not exist")
        loaded = _read_yaml(path, "config file")
    given = _merge(loaded, parse_set(sets or []))
    data = dict(defaults or {})
    if cls is ExperimentConfig:  # the map is known only once every layer is read
        data = _merge(data, map_defaults(_merge(data, given)))
        data = _merge(data, map_settings(_merge(data, given)))
    cfg = from_dict(cls, _merge(data, given))
    return cfg.validate() if hasattr(cfg, "validate") else cfg
