"""The config dataclasses, each field with its declared bound, and the key helpers of messages.

``conf/`` YAML files only pick groups and override these defaults.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any

from omegaconf import II, MISSING, DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

LOGGER_BACKENDS = ("csv", "tensorboard", "wandb", "mlflow", "none")


class ConfigError(ValueError):
    """An invalid configuration, found before training starts."""

    __module__ = "torchrl_stages.config"  # where it is imported from


def check(ok: bool, key: str, value: object, rule: str, fix: str) -> None:
    """Raises :class:`ConfigError` ``"{key}={value!r}: {rule}. Fix: {fix}"`` unless ``ok``.

    Examples:
        >>> check(False, "seed", -1, "must be >= 0", "set seed=0")
        Traceback (most recent call last):
        ...
        torchrl_stages.config.ConfigError: seed=-1: must be >= 0. Fix: set seed=0
    """
    if not ok:
        raise ConfigError(f"{key}={value!r}: {rule}. Fix: {fix}")


@dataclass(frozen=True)
class Bound:
    """The values a config field accepts: a number in ``[low, high]`` (ends open or not), one of
    ``choices``, a full match of ``pattern`` (``text`` names it), or anything (``free``). A list
    value needs one entry at least, each inside; ``None`` is left to the field's type.

    Examples:
        >>> Bound(low=0, low_open=True).problem(0), Bound(choices=("a", "b")).problem("c")
        ('must be > 0', 'unknown (known: a, b)')
    """

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[Any, ...] = ()
    pattern: str | None = None
    text: str = ""
    free: bool = False
    example: Any = None

    def rule(self) -> str:
        if self.choices:
            return f"unknown (known: {', '.join(map(str, self.choices))})"
        if self.pattern:
            return f"must be {self.text}"
        if self.high is None:
            return f"must be {'>' if self.low_open else '>='} {self.low}"
        left, right = "(" if self.low_open else "[", ")" if self.high_open else "]"
        return f"must be in {left}{self.low}, {self.high}{right}"

    def allows(self, value: Any) -> bool:
        if self.free or value is None:
            return True
        if isinstance(value, list | ListConfig):
            return len(value) > 0 and all(map(self.allows, value))
        if self.choices:
            return value in self.choices
        if self.pattern:
            return re.fullmatch(self.pattern, str(value)) is not None
        above = value > self.low or (value == self.low and not self.low_open)
        if self.high is None:
            return above
        return above and (value < self.high or (value == self.high and not self.high_open))

    def problem(self, value: Any) -> str | None:
        """Why ``value`` is refused (``None``: it is allowed)."""
        if self.allows(value):
            return None
        if isinstance(value, list | ListConfig):
            return f"needs at least one entry, each {self.rule().removeprefix('must be ')}"
        return self.rule()

    def fix(self, key: str) -> str:
        shown = str(self.example).replace(" ", "")
        if self.example is None or shown == MISSING or "${" in shown or self.high is not None:
            return f"set {key} to a value in that range"
        return f"set {key}={shown}"


def bound(default: Any = MISSING, *, factory: Callable[[], Any] | None = None, **limits) -> Any:
    """A dataclass field of ``default`` (or ``factory()``) whose values must be inside ``limits``
    (:class:`Bound`'s keys)."""
    metadata = {"bound": Bound(**limits, example=factory() if factory else default)}
    if factory is not None:
        return field(default_factory=factory, metadata=metadata)
    return field(default=default, metadata=metadata)


def positive(default: Any = MISSING, **kwargs) -> Any:
    return bound(default, low=0, low_open=True, **kwargs)


def non_negative(default: Any = MISSING, **kwargs) -> Any:
    return bound(default, low=0, **kwargs)


def in_range(low: float, high: float, default: Any, **kwargs) -> Any:
    """A number in ``[low, high]``; ``low_open`` / ``high_open`` leave an end out."""
    return bound(default, low=low, high=high, **kwargs)


def one_of(*choices: Any, default: Any) -> Any:
    return bound(default, choices=choices)


def flag(default: bool) -> Any:
    return bound(default, choices=(True, False))


def torch_device(default: str) -> Any:
    """A torch device name; :func:`~torchrl_stages.config.checks.check_device` asks torch for it."""
    return bound(default, pattern=r"cpu|mps|cuda(:\d+)?", text="cpu, cuda, cuda:<index> or mps")


def free(default: Any = MISSING, *, factory: Callable[[], Any] | None = None) -> Any:
    """A field that takes any value of its type (a name, a free-form mapping)."""
    return bound(default, factory=factory, free=True)


def check_bounds(node: Any, schema: type, prefix: str) -> None:
    """Refuses every key of ``node`` (at ``prefix``) outside the bound its ``schema`` field
    declares, nested blocks included; keys ``node`` lacks, ``???`` and fields without a bound
    (a user's own config class) are left alone."""
    for f in fields(schema):
        if f.name not in node or OmegaConf.is_missing(node, f.name):
            continue
        key, value = f"{prefix}.{f.name}" if prefix else f.name, node[f.name]
        if is_dataclass(f.default_factory) and value is not None:
            check_bounds(value, f.default_factory, key)
        elif "bound" in f.metadata:
            declared = f.metadata["bound"]
            problem = declared.problem(value)
            check(problem is None, key, value, str(problem), declared.fix(key))


def nearest(name: str, known: Iterable[str]) -> str | None:
    """The name of ``known`` closest to ``name`` (a typo of it), ``None`` when none is close.

    Examples:
        >>> nearest("lrr", ["lr", "gamma", "tau"]), nearest("xyz", ["lr", "gamma"])
        ('lr', None)
    """
    found = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return found[0] if found else None


def unknown_key(
    prefix: str,
    name: str,
    value: object,
    known: Collection[str],
    owner: str,
    fix: str,
    what: str = "a key",
) -> ConfigError | None:
    """The error of ``{prefix}.{name}`` unless ``name`` is one of ``known`` (``what`` of
    ``owner``), naming the nearest known key, else ending with ``fix``.

    Examples:
        >>> print(unknown_key("task.stages.s0", "lrr", 1e-3, ["lr", "gamma"], "dqn", "drop it"))
        task.stages.s0.lrr=0.001: not a key of dqn. Fix: did you mean task.stages.s0.lr?
    """
    if name in known:
        return None
    close = nearest(name, known)
    hint = f"did you mean {prefix}.{close}?" if close else fix
    return ConfigError(f"{prefix}.{name}={value!r}: not {what} of {owner}. Fix: {hint}")


def schema_keys(schema: type) -> list[str]:
    return [f.name for f in fields(schema)]


class StageChecks:
    """An algorithm's own checks of one stage's keys (``Learner.validate``), each error naming
    ``{key}.{field}`` and the fix.

    Examples:
        >>> StageChecks("task.stages.s0", {"lr": 0.0}).positive("lr", 1e-3)
        Traceback (most recent call last):
        ...
        torchrl_stages.config.ConfigError: task.stages.s0.lr=0.0: must be > 0. Fix: ...
    """

    def __init__(self, key: str, cfg: Any) -> None:
        self.key, self.cfg = key, cfg

    def __call__(self, ok: bool, field: str, rule: str, fix: str) -> None:
        check(ok, f"{self.key}.{field}", self.cfg[field], rule, fix)

    def positive(self, field: str, example: object) -> None:
        self(self.cfg[field] > 0, field, "must be > 0", f"set {self.key}.{field}={example}")

    def non_negative(self, field: str) -> None:
        self(self.cfg[field] >= 0, field, "must be >= 0", f"set {self.key}.{field}=0 or more")

    def fraction(self, field: str, low_open: bool = False) -> None:
        problem = Bound(low=0, high=1, low_open=low_open).problem(self.cfg[field])
        fix = f"set {self.key}.{field} to a value in that range"
        self(problem is None, field, str(problem), fix)


@dataclass
class StageConfig:
    """Hyper-parameters shared by every stage learner; budgets count env frames (summed over
    the stage env's batch)."""

    algo: str = free()  # a registered algorithm (torchrl_stages.learners.ALGORITHMS)
    # your own learner class instead of the algorithm's (it keeps the keys of `algo`):
    # {_target_: my_pkg.MyLearner, my_key: 1}; the class is called with (cfg, specs, compile=,
    # my_key=1) and subclasses torchrl_stages.learners.Learner
    learner: dict[str, Any] = free(factory=dict)
    gamma: float = in_range(0, 1, 0.99, low_open=True)  # this stage's discount
    lr: float = positive(1e-3)  # learning rate (the critic's, for actor-critic algorithms)
    # every learning rate decays linearly to this fraction of its start value over `frames`
    # (1: constant)
    lr_end_factor: float = in_range(0, 1, 1.0)
    max_grad_norm: float | None = positive(None)  # clip each optimizer's gradient norm (null: off)
    # torch.optim.Adam(fused=True): the same update up to float rounding, cheaper for small
    # networks; false: torch's default Adam
    fused_adam: bool = flag(False)
    num_cells: list[int] = positive(factory=lambda: [64, 64])  # hidden layers of each MLP
    # octaves of sin/cos input encoding before each MLP (0: raw input)
    fourier_features: int = non_negative(0)
    # CNN over image observations (C, H, W), one entry per conv layer (padding kernel // 2); its
    # flattened features join the vector observations before the MLP. Unused without images.
    cnn_channels: list[int] = positive(factory=lambda: [16, 32])
    cnn_kernels: list[int] = positive(factory=lambda: [3, 3])
    cnn_strides: list[int] = positive(factory=lambda: [1, 2])
    num_envs: int = positive(64)  # batch size of the stage's training env
    frames: int = positive(100_000)  # env-frame budget of the stage
    frames_per_batch: int = positive(256)  # frames per collector batch
    init_random_frames: int = non_negative(1_000)  # uniformly random actions before learning
    buffer_size: int = positive(100_000)  # replay-buffer capacity (transitions)
    batch_size: int = positive(256)  # replay samples per gradient step
    updates_per_batch: int = positive(4)  # gradient steps per collected batch
    # frames over which the exploration schedule anneals (epsilon-greedy, Gaussian noise)
    annealing_frames: int = non_negative(20_000)
    tau: float = in_range(0, 1, 0.005, low_open=True)  # soft target-network update rate
    eval_every: int = non_negative(5_000)  # frames between greedy evaluations (0: never)
    # greedy episodes per stage evaluation, from random starts in the stage (or all of its
    # start states where the env enumerates them, e.g. GridWorldEnv.start_states)
    eval_episodes: int = positive(64)
    eval_max_steps: int | None = positive(None)  # longer greedy episodes fail (null: env limit)
    # early stop once stage success >= this (null: off)
    success_threshold: float | None = in_range(0, 1, None)
    # ... and |V(s_0) - discounted greedy return| <= this over the evaluation's starts, reduced
    # by `value_error_reduce` (null: not checked)
    value_tolerance: float | None = non_negative(None)
    value_error_reduce: str = one_of("mean", "max", default="mean")  # over the start states
    patience: int = positive(1)  # consecutive evaluations that must meet the early stop
    min_frames: int = non_negative(0)  # no early stop before this many frames
    keep_best: bool = flag(True)  # budget exhausted: restore the best evaluated weights
    # "best" = highest success, then: value_error (lowest) | return (highest mean discounted)
    keep_best_by: str = one_of("value_error", "return", default="value_error")


@dataclass
class TaskConfig:
    """A multi-stage task: its env and one learner config per stage, in stage order."""

    name: str = free()
    # keyword arguments of the multi-stage env; `_target_` names its class. The schedule adds
    # `batch_size` and `start_stage` when it builds per-stage envs.
    env: dict[str, Any] = free(factory=dict)
    # whole-task starts used for the final evaluation (passed to the env on top of `env`)
    eval_env: dict[str, Any] = free(factory=dict)
    stages: dict[str, Any] = free(factory=dict)
    # every stage's keys when the env says how many stages there are (its num_stages): stages
    # s0..s<N-1>, each this template with its own task.stages.s<k> keys over it. Empty:
    # `stages` lists them all
    stage_template: dict[str, Any] = free(factory=dict)
    eval_episodes: int = positive(100)  # this task's default for eval.episodes
    # this task's default for `threads` (torch intra-op threads): one beside a busy process is
    # 3-4x faster than two (scripts/benchmark_threads.py, docs/speed.md)
    threads: int = positive(1)
    # whether the env can start an episode inside a chosen stage (`start_stage=k`); without
    # stage starts only schedule=joint applies, as one phase from the task's own starts
    stage_starts: bool = flag(True)


@dataclass
class ScheduleConfig:
    """How the stages are trained: ``backward`` (stage N-1 alone, frozen, then N-2 against its
    value, ...), ``joint`` (the paper's Algorithm 1: every stage learns from whole-task episodes,
    phase k starting in stage k) or ``flat`` (one learner over the whole task, each transition
    discounted by its stage's gamma: the end-to-end baseline)."""

    name: str = free("backward")  # a registered schedule (get_schedule names them)


@dataclass
class LoggerConfig:
    """Where metrics go, through ``torchrl.record.loggers.get_logger``."""

    backend: str = one_of(*LOGGER_BACKENDS, default="csv")
    exp_name: str = free("${task.name}")
    project: str = free("torchrl-stages")  # wandb project / mlflow experiment


@dataclass
class EvalConfig:
    """Whole-task evaluation of the stacked greedy policy after training, from every
    whole-task start the env enumerates, else from ``episodes`` random ones."""

    episodes: int = positive(II("task.eval_episodes"))  # default: the task's
    plots: bool = flag(True)
    # follow the whole task during training: at every evaluation of stage 0 (backward), of
    # phase 0 (joint) or of the flat learner, log eval/task/{success_rate, seconds} against the
    # frames of all stages so far
    probe: bool = flag(False)


@dataclass
class ObjectiveConfig:
    """The entry of ``eval.json`` a run is judged by (:func:`objective_value`), and whether
    higher is better; a Hydra sweeper's own direction must agree."""

    metric: str = one_of("success_rate", "mean_return", "mean_steps", default="success_rate")
    direction: str = one_of("maximize", "minimize", default="maximize")


@dataclass
class TuneConfig:
    """The ``tune`` block of ``stages-tune``: an Optuna study of ``objective`` over ``params``,
    each trial a ``stages-train`` run.

    ``params`` maps a config key (``task.stages.s3.lr``, ``++all_stages.lr``) or a config
    group (``algo@task.stages.s0``, ``schedule``) to its range: ``{low: 1e-4, high: 1e-2,
    log: true}`` (ints when ``low`` and ``high`` are; optional ``step``) or ``{choices: [dqn,
    sac]}``.
    """

    study_name: str = free("${task.name}")
    # Optuna storage: an RDB URL (sqlite:///study.db, postgresql://...) or a journal file
    # (study.log: several processes, NFS); relative paths from where the command is launched
    storage: str = free("sqlite:///study.db")
    n_trials: int = positive(20)  # trials this command runs (a rerun adds as many to the study)
    sampler: str = one_of("tpe", "random", default="tpe")
    # the sampler's seed (plus the number of trials already in the study)
    seed: int = non_negative(II("seed"))
    pruner: str = one_of("median", "threshold", "none", default="median")
    startup_trials: int = non_negative(5)  # median: trials that must finish before any is pruned
    warmup_steps: int = non_negative(0)  # stage evaluations of a trial before it may be pruned
    # threshold: prune a trial at a stage evaluation whose success rate is below this
    prune_below: float | None = in_range(0, 1, None, low_open=True)
    # the search space: {key: range}; +tune.params.<key>={...} adds one key; presets: tune=<name>
    params: Any = free(None)
    plots: bool = flag(True)  # the study summary's figures (summary_*.png)


@dataclass
class TrainConfig:
    """Root config of ``stages-train``."""

    task: TaskConfig = field(default_factory=TaskConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    objective: ObjectiveConfig = field(default_factory=ObjectiveConfig)
    seed: int = non_negative(0)
    # several seeds of this config in one process, their networks stacked (backward and flat
    # schedules; dqn, ddpg, td3): seeds=[0,1,2] writes hydra.run.dir/seed_<s>/, one run
    # directory per seed, and the sweep summary over them (null: one run, `seed`)
    seeds: list[int] | None = non_negative(None)
    device: str = torch_device("cpu")  # cpu | cuda | cuda:<index> | mps
    # torch intra-op threads; default: the task's (task.threads). Use 1 per job when a launcher
    # runs several jobs at once on the same cores
    threads: int = positive(II("task.threads"))
    progress: bool = flag(True)  # tqdm bar per stage (hidden anyway when stderr is not a TTY)
    # frames between two checkpoints of the stage in progress (0: none)
    checkpoint_every: int = non_negative(50_000)
    checkpoint_keep: int = positive(2)  # newest checkpoints kept per stage
    # torch.compile of every learner's loss: auto (off on CPU, reduce-overhead on a GPU) | off |
    # default | reduce-overhead | max-autotune
    compile: str = one_of(
        "auto", "off", "default", "reduce-overhead", "max-autotune", default="auto"
    )
    resume: bool = flag(False)  # continue the run in hydra.run.dir (same overrides otherwise)
    # a directory of finished stages shared by runs: a stage whose identity (its config, the
    # env, the seed, the stages after it) is there is loaded instead of trained, and every stage
    # trained is added. schedule=backward only; `stages-store ls|rm|prune DIR` manages it
    stage_store: str | None = free(None)
    # a run directory whose finished stages are taken where their identity is unchanged: a
    # changed key of stage k retrains stage k and the stages before it (schedule=backward)
    init_from: str | None = free(None)
    overwrite: bool = flag(False)  # replace the run in hydra.run.dir
    # keys set in every task.stages.<name>, over the task's own; a key set for one stage on the
    # command line keeps its value. Emptied once applied (apply_all_stages)
    all_stages: dict[str, Any] = free(factory=dict)


@dataclass
class TuneAppConfig(TrainConfig):
    """Root config of ``stages-tune``: that of ``stages-train`` and the ``tune`` block."""

    tune: TuneConfig = field(default_factory=TuneConfig)


def objective_value(result: dict[str, Any], cfg: Any) -> float:
    """``eval.json``'s entry named by ``objective.metric`` (NaN when undefined, which Optuna
    records as a failed trial).

    Examples:
        >>> cfg = OmegaConf.create({"objective": {"metric": "mean_steps"}})
        >>> objective_value({"success_rate": 1.0, "mean_steps": 12.5}, cfg)
        12.5
    """
    objective = cfg.get("objective")
    value = result.get("success_rate" if objective is None else objective.metric)
    return float("nan") if value is None else float(value)


def as_dataclass(cfg: Any) -> Any:
    """A structured config node as an instance of its schema, interpolations resolved (a
    dataclass read costs nanoseconds, a ``DictConfig`` read ~10 us); anything else as given.

    Examples:
        >>> cfg = as_dataclass(OmegaConf.structured(StageConfig(algo="mine", gamma=0.9)))
        >>> type(cfg).__name__, cfg.gamma
        ('StageConfig', 0.9)
    """
    if isinstance(cfg, DictConfig) and is_dataclass(OmegaConf.get_type(cfg)):
        try:
            return OmegaConf.to_object(cfg)
        except OmegaConfBaseException:  # e.g. a missing value: keep the node (errors on read)
            return cfg
    return cfg
