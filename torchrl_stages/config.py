"""Configuration schemas and the checks every config value goes through.

The YAML files in ``conf/`` only pick groups and override these defaults; the dataclasses are the
single source of truth for what a key means and what it defaults to. Every stage of a task is one
entry of ``task.stages`` holding an algorithm's schema (a subclass of :class:`StageConfig`
defined next to its learner in ``torchrl_stages/learners/<algo>.py``), so
``task.stages.s3.lr=3e-4`` and ``algo@task.stages.s0=<algo>`` work from the command line, on a
template task (``task=gym``, whose stages come from the env) too. A key its algorithm lacks,
written with Hydra's ``+`` or without, is refused before training naming the nearest one
(:func:`unknown_key`, ``torchrl_stages.validate``).
"""

from __future__ import annotations

import copy
import difflib
from collections.abc import Collection, Iterable, Iterator
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any

from omegaconf import II, MISSING, DictConfig, OmegaConf, open_dict
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException


class ConfigError(ValueError):
    """An invalid configuration, found before training starts."""


def check(ok: bool, key: str, value: object, rule: str, fix: str) -> None:
    """Raises :class:`ConfigError` ``"{key}={value!r}: {rule}. Fix: {fix}"`` unless ``ok``.

    Examples:
        >>> check(True, "seed", 0, "must be >= 0", "set seed=0")
        >>> check(False, "seed", -1, "must be >= 0", "set seed=0")
        Traceback (most recent call last):
        ...
        torchrl_stages.config.ConfigError: seed=-1: must be >= 0. Fix: set seed=0
    """
    if not ok:
        raise ConfigError(f"{key}={value!r}: {rule}. Fix: {fix}")


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
    """The error of key ``{prefix}.{name}`` unless ``name`` is one of ``known`` (``what`` of
    ``owner``): one line naming the nearest known key, else ending with ``fix``.

    Examples:
        >>> print(unknown_key("task.stages.s0", "lrr", 1e-3, ["lr", "gamma"], "dqn", "drop it"))
        task.stages.s0.lrr=0.001: not a key of dqn. Fix: did you mean task.stages.s0.lr?
        >>> unknown_key("task.stages.s0", "lr", 1e-3, ["lr", "gamma"], "dqn", "drop it") is None
        True
    """
    if name in known:
        return None
    close = nearest(name, known)
    hint = f"did you mean {prefix}.{close}?" if close else fix
    return ConfigError(f"{prefix}.{name}={value!r}: not {what} of {owner}. Fix: {hint}")


def schema_keys(schema: type) -> list[str]:
    """The keys of a config dataclass (a stage's algorithm's, :class:`StageConfig`'s)."""
    return [f.name for f in fields(schema)]


class StageChecks:
    """Range checks of one stage's keys, each error naming ``{key}.{field}`` and the fix.

    Examples:
        >>> checks = StageChecks("task.stages.s0", {"lr": 0.0, "gamma": 0.9})
        >>> checks.fraction("gamma", low_open=True)
        >>> checks.positive("lr", 1e-3)
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
        v = self.cfg[field]
        ok = (0 < v <= 1) if low_open else (0 <= v <= 1)
        rule = "must be in (0, 1]" if low_open else "must be in [0, 1]"
        self(ok, field, rule, f"set {self.key}.{field} to a value in that range")


@dataclass
class StageConfig:
    """Hyper-parameters shared by every stage learner.

    Budgets are counted in env frames (summed over the stage env's batch).
    """

    algo: str = MISSING  # a registered algorithm (torchrl_stages.learners.ALGORITHMS)
    # your own learner class instead of the algorithm's (it keeps the keys of `algo`):
    # {_target_: my_pkg.MyLearner, my_key: 1}; the class is called with (cfg, specs, compile=,
    # my_key=1) and subclasses torchrl_stages.learners.Learner
    learner: dict[str, Any] = field(default_factory=dict)
    gamma: float = 0.99  # this stage's discount (also used for its transition reward)
    lr: float = 1e-3  # learning rate (the critic's, for actor-critic algorithms)
    # every learning rate decays linearly to this fraction of its start value over `frames`
    # (1: constant); late, small steps let the values settle instead of oscillating
    lr_end_factor: float = 1.0
    max_grad_norm: float | None = None  # clip each optimizer's gradient norm (null: no clip)
    # Adam's fused kernel (torch.optim.Adam(fused=True): one op for all parameters instead of
    # ~10 per tensor): the same update up to float rounding, cheaper where the networks are
    # small; false: torch's default Adam
    fused_adam: bool = False
    num_cells: list[int] = field(default_factory=lambda: [64, 64])  # hidden layers of each MLP
    fourier_features: int = 0  # octaves of sin/cos input encoding before each MLP (0: raw input)
    # CNN over image observations (C, H, W), one entry per conv layer (padding kernel // 2); its
    # flattened features join the vector observations before the MLP. Unused without images.
    cnn_channels: list[int] = field(default_factory=lambda: [16, 32])
    cnn_kernels: list[int] = field(default_factory=lambda: [3, 3])
    cnn_strides: list[int] = field(default_factory=lambda: [1, 2])
    num_envs: int = 64  # batch size of the stage's training env
    frames: int = 100_000  # env-frame budget of the stage
    frames_per_batch: int = 256  # frames per collector batch
    init_random_frames: int = 1_000  # uniformly random actions before learning starts
    buffer_size: int = 100_000  # replay-buffer capacity (transitions)
    batch_size: int = 256  # replay samples per gradient step
    updates_per_batch: int = 4  # gradient steps per collected batch
    # frames over which the exploration schedule anneals (epsilon-greedy, Gaussian noise;
    # algorithms that learn their exploration, such as SAC's entropy, have none)
    annealing_frames: int = 20_000
    tau: float = 0.005  # soft target-network update rate
    eval_every: int = 5_000  # frames between greedy evaluations of the stage (0: never)
    # greedy episodes per stage evaluation, from random starts in the stage; an env that can
    # enumerate the stage's start states (GridWorldEnv.start_states) is evaluated from all of them
    eval_episodes: int = 64
    eval_max_steps: int | None = None  # longer greedy stage episodes fail (null: env time limit)
    success_threshold: float | None = None  # early stop once stage success >= this (null: off)
    # ... and |V(s_0) - discounted greedy return| <= this over the evaluation's starts, reduced
    # by `value_error_reduce` (null: not checked)
    value_tolerance: float | None = None
    value_error_reduce: str = "mean"  # mean | max over the evaluation's start states
    patience: int = 1  # consecutive evaluations that must meet the early-stop criterion
    min_frames: int = 0  # no early stop before this many frames
    keep_best: bool = True  # budget exhausted: restore the best evaluated weights
    # "best" = highest success, then: value_error (lowest) | return (highest mean discounted)
    keep_best_by: str = "value_error"


@dataclass
class TaskConfig:
    """A multi-stage task: its env and one learner config per stage, in stage order."""

    name: str = MISSING
    # Keyword arguments of the multi-stage env; `_target_` names its class. The schedule adds
    # `batch_size` and `start_stage` when it builds per-stage envs.
    env: dict[str, Any] = field(default_factory=dict)
    # Whole-task starts used for the final evaluation (passed to the env on top of `env`).
    eval_env: dict[str, Any] = field(default_factory=dict)
    stages: dict[str, Any] = field(default_factory=dict)
    # every stage's keys when the env says how many stages there are (its num_stages): the task
    # then has stages s0..s<N-1>, each this template with its own task.stages.s<k> keys over it
    # (expand_stage_template). Empty: `stages` lists them all
    stage_template: dict[str, Any] = field(default_factory=dict)
    eval_episodes: int = 100  # this task's default for eval.episodes
    # this task's default for `threads` (torch intra-op threads). 1 for every shipped task: two
    # threads train the manipulator 1.5x and cargo 1.2x faster on two free cores, but 3-4x slower
    # than one beside a busy process (scripts/benchmark_threads.py, docs/speed.md)
    threads: int = 1
    # whether the env can start an episode inside a chosen stage (`start_stage=k`); without
    # stage starts only schedule=joint applies, as one phase from the task's own starts
    stage_starts: bool = True


@dataclass
class ScheduleConfig:
    """How the stages are trained.

    * ``backward``: stage N-1 alone, frozen, then N-2 against its value, ... (each stage's own
      budget, early stop and evaluation from its start states).
    * ``joint``: the paper's Algorithm 1. Phase k (k = N-1 .. 0) runs whole-task episodes from
      stage-k starts with the stacked exploration policy; each transition goes to the replay
      buffer of the stage of s_t; every collected batch, every stage with data takes its
      ``updates_per_batch`` gradient steps, last stage first, with transition rewards computed
      at sampling time from the next stage's current target networks. Phase k uses stage k's
      collection, budget (``frames``), evaluation and early-stop keys, its evaluations being
      whole-task episodes from stage-k starts.
    * ``flat``: one learner (stage 0's config, the sum of the stages' budgets) over the whole
      task, no stages: the end-to-end baseline of the paper's Discussion. Each transition is
      discounted with the gamma of its stage, so it optimizes the same objective.
    """

    name: str = "backward"  # backward | joint | flat


@dataclass
class LoggerConfig:
    """Where metrics go, through ``torchrl.record.loggers.get_logger``."""

    backend: str = "csv"  # csv | tensorboard | wandb | mlflow | none
    exp_name: str = "${task.name}"
    project: str = "torchrl-stages"  # wandb project / mlflow experiment


@dataclass
class EvalConfig:
    """Whole-task evaluation of the stacked greedy policy after training.

    Episodes start from the task's whole-task starts: every one of them once when the env can
    enumerate them (the grid world's column 0), else ``episodes`` random ones.
    """

    episodes: int = II("task.eval_episodes")  # default: the task's (e.g. 1000 for cargo)
    plots: bool = True
    # follow the whole task during training: at every evaluation of stage 0 (backward), of
    # phase 0 (joint) or of the flat learner, log eval/task/{success_rate, seconds} (and the
    # grid world's path_optimal, value_error) against the frames of all stages so far
    probe: bool = False


@dataclass
class ObjectiveConfig:
    """The number a run is judged by: one entry of its ``eval.json``, from the whole-task
    evaluation after training (:func:`objective_value`). ``stages-tune`` optimizes it in
    ``direction`` (:class:`TuneConfig`), and ``stages-train`` returns it to a Hydra sweeper.

    ``direction`` says whether higher is better; a Hydra sweeper that optimizes a direction of
    its own (``hydra.sweeper.direction``) must agree with it, which is checked before any job
    runs.
    """

    metric: str = "success_rate"  # success_rate | mean_return | mean_steps
    direction: str = "maximize"  # maximize | minimize


@dataclass
class TuneConfig:
    """The ``tune`` block of ``stages-tune`` (:mod:`torchrl_stages.tune`): an Optuna
    study that optimizes ``objective`` over ``params``, each trial a ``stages-train`` run.

    ``params`` maps a config key (``task.stages.s3.lr``; ``++all_stages.lr`` adds a key, here
    one value for every stage) or a config group (``algo@task.stages.s0``, ``schedule``) to its
    range: ``{low: 1e-4, high: 1e-2, log: true}`` (floats; ints when ``low`` and ``high`` are
    ints; optional ``step``) or ``{choices: [dqn, sac]}``. Trials report each stage
    evaluation's success rate, and the pruner stops the hopeless ones.
    """

    study_name: str = "${task.name}"
    # Optuna storage: an RDB URL (sqlite:///study.db, postgresql://...) or a journal file
    # (study.log: several processes, NFS); relative paths from where the command is launched
    storage: str = "sqlite:///study.db"
    n_trials: int = 20  # trials this command runs (a rerun adds as many to the study)
    sampler: str = "tpe"  # tpe | random
    # the sampler's seed (plus the number of trials already in the study, so that a rerun
    # does not draw the same values again)
    seed: int = II("seed")
    pruner: str = "median"  # median | threshold | none
    # median: trials that must finish before any is pruned
    startup_trials: int = 5
    warmup_steps: int = 0  # stage evaluations of a trial before it may be pruned
    # threshold: prune a trial at a stage evaluation whose success rate is below this
    prune_below: float | None = None
    # the search space: {key: range} ('tune.params={task.stages.s3.lr: {low: 1e-4, high: 1e-2,
    # log: true}}'; +tune.params.<key>={...} adds one key); presets: tune=<name> (conf/tune/)
    params: Any = None
    plots: bool = True  # the study summary's figures (summary_*.png)


@dataclass
class TrainConfig:
    """Root config of ``stages-train``."""

    task: TaskConfig = field(default_factory=TaskConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    objective: ObjectiveConfig = field(default_factory=ObjectiveConfig)
    seed: int = 0
    # several seeds of this config in one process, their networks stacked (backward and flat
    # schedules; algorithms that stack seeds: dqn, ddpg, td3): seeds=[0,1,2] writes
    # hydra.run.dir/seed_<s>/, one ordinary run directory per seed, and the sweep summary over
    # them (null: one run, `seed`)
    seeds: list[int] | None = None
    device: str = "cpu"
    # torch intra-op threads; default: the task's (task.threads). Use 1 per job when a launcher
    # runs several jobs at once on the same cores
    threads: int = II("task.threads")
    progress: bool = True  # tqdm bar per stage (hidden anyway when stderr is not a TTY)
    # frames between two checkpoints of the stage in progress (0: none); a resumed run loses at
    # most that much of the stage (about a minute of training on the shipped tasks)
    checkpoint_every: int = 50_000
    checkpoint_keep: int = 2  # newest checkpoints kept per stage
    # torch.compile of every learner's loss: auto (measured: off on CPU, where compiling
    # costs more than it saves on these small networks; reduce-overhead, i.e. CUDA graphs, on a
    # GPU) | off | default | reduce-overhead | max-autotune
    compile: str = "auto"
    resume: bool = False  # continue the run in hydra.run.dir (same overrides otherwise)
    # a directory of finished stages shared by runs (a sweep's jobs; local or on a cluster file
    # system): a stage whose identity (its config, the env, the seed, the stages after it) is
    # there is loaded instead of trained, and every stage trained is added. schedule=backward
    # only; `stages-store ls|rm|prune DIR` manages it (null: off)
    stage_store: str | None = None
    # a run directory whose finished stages are taken where their identity is unchanged: a
    # changed key of stage k retrains stage k and the stages before it (schedule=backward)
    init_from: str | None = None
    overwrite: bool = False  # replace the run in hydra.run.dir
    # keys set in every task.stages.<name>, whatever the task and its stages (those added on
    # the command line too), over the task's own; a key set for one stage on the command line
    # keeps its value. experiment=smoke puts its tiny budget here. Emptied once applied
    # (apply_all_stages): a run's config.yaml holds each stage's values
    all_stages: dict[str, Any] = field(default_factory=dict)


@dataclass
class TuneAppConfig(TrainConfig):
    """Root config of ``stages-tune``: that of ``stages-train`` and the ``tune`` block."""

    tune: TuneConfig = field(default_factory=TuneConfig)


def objective_value(result: dict[str, Any], cfg: Any) -> float:
    """The number a run is judged by: ``eval.json``'s entry named by ``objective.metric`` (NaN
    when undefined, which Optuna records as a failed trial).

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"objective": {"metric": "mean_steps"}})
        >>> objective_value({"success_rate": 1.0, "mean_steps": 12.5}, cfg)
        12.5
    """
    objective = cfg.get("objective")
    value = result.get("success_rate" if objective is None else objective.metric)
    return float("nan") if value is None else float(value)


def as_dataclass(cfg: Any) -> Any:
    """A structured config node (e.g. a composed ``task.stages.<name>``) as an instance of its
    schema, interpolations resolved; anything else as given.

    Reading a field of a plain dataclass costs nanoseconds where a ``DictConfig`` read costs
    about 10 microseconds, and a learner's update reads several.

    Examples:
        >>> from omegaconf import OmegaConf
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


def apply_all_stages(cfg: DictConfig, keep: Iterable[tuple[str, str]] = ()) -> DictConfig:
    """A copy of ``cfg`` with ``cfg.all_stages``'s keys set in every ``task.stages.<name>``,
    except the ``(stage, key)`` pairs of ``keep`` (what the command line set for one stage),
    and ``all_stages`` emptied (applying it again changes nothing). A key that a stage's
    algorithm does not have is a :class:`ConfigError`.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"task": {"stages": {"a": {"frames": 9}, "b": {"frames": 9}}},
        ...                         "all_stages": {"frames": 1024}})
        >>> cfg = apply_all_stages(cfg, keep=[("b", "frames")])
        >>> cfg.task.stages.a.frames, cfg.task.stages.b.frames, dict(cfg.all_stages)
        (1024, 9, {})
    """
    if not cfg.get("all_stages"):
        return cfg
    cfg = copy.deepcopy(cfg)  # the caller's config is left as it was
    every, kept = cfg.all_stages, set(keep)
    stages = dict(cfg.task.stages.items())
    if cfg.task.get("stage_template"):  # stages made from the template get them from there,
        stages = {k: v for k, v in stages.items() if "algo" in v}  # not from their own keys
        stages["stage_template"] = cfg.task.stage_template
    for name, stage in stages.items():
        schema = OmegaConf.get_type(stage)
        for key, value in every.items():
            if (name, key) in kept:
                continue
            try:
                if is_dataclass(schema) and key not in schema_keys(schema):  # an open node
                    raise ConfigKeyError(key)  # would take it: its schema does not
                stage[key] = value
            except OmegaConfBaseException as err:
                where = "task.stage_template" if name == "stage_template" else f"task.stages.{name}"
                close = nearest(key, schema_keys(schema)) if is_dataclass(schema) else None
                fix = (
                    f"did you mean all_stages.{close}?"
                    if close and close not in every
                    else f"set it for the stages that have it (task.stages.<stage>.{key}=...)"
                )
                raise ConfigError(
                    f"all_stages.{key}={value!r}: {where} "
                    f"({getattr(schema, '__name__', schema)}) cannot take it "
                    f"({type(err).__name__}). Fix: {fix}"
                ) from None
    cfg.all_stages = {}
    return cfg


def stage_name(stage: int) -> str:
    """The name of stage ``stage`` in a task whose stages come from its template: ``s<k>``."""
    return f"s{stage}"


def expand_stage_template(task: DictConfig, num_stages: int) -> DictConfig:
    """A copy of the task config ``task`` with stages ``s0..s<num_stages-1>``, each
    ``task.stage_template`` with the keys ``task.stages.s<k>`` already has over it (a stage's
    own overrides); ``task`` itself when it has no template. Applying it again changes nothing.
    A stage named otherwise, or past the env's last stage, is a :class:`ConfigError`.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> task = OmegaConf.create({"stage_template": {"algo": "dqn", "lr": 1e-3},
        ...                          "stages": {"s2": {"lr": 5e-4}}})
        >>> stages = expand_stage_template(task, 3).stages
        >>> list(stages), stages.s0.lr, stages.s2.lr, stages.s2.algo
        (['s0', 's1', 's2'], 0.001, 0.0005, 'dqn')
    """
    if not task.get("stage_template"):
        return task
    names = [stage_name(k) for k in range(num_stages)]
    extra = [name for name in task.stages if name not in names]
    if extra:
        raise ConfigError(
            f"task.stages.{extra[0]}: the env has {num_stages} stages, named "
            f"{', '.join(names)} (each task.stage_template with its own keys over it). Fix: "
            f"set that stage's keys as task.stages.<{names[0]}..{names[-1]}>.<key>=..."
        )
    task = copy.deepcopy(task)
    stages = {}
    for name in names:
        own = task.stages.get(name) or {}
        try:
            stages[name] = OmegaConf.merge(task.stage_template, own)
        except OmegaConfBaseException as err:
            raise ConfigError(
                f"task.stages.{name}: its keys do not fit task.stage_template "
                f"({type(err).__name__}: {str(err).splitlines()[0]}). Fix: set only keys the "
                "stage's algorithm has"
            ) from None
    with open_dict(task):
        task.stages = stages
    return task


def stage_keys_set(overrides: Iterable[str]) -> set[tuple[str, str]]:
    """The ``(stage, key)`` pairs that command-line ``overrides`` set directly
    (``task.stages.<stage>.<key>=...``, with or without ``+``/``++``).

    Examples:
        >>> sorted(stage_keys_set(["task.stages.s0.frames=10", "+task.stages.s1.lr=1e-3",
        ...                        "algo@task.stages.s2=sac", "seed=1"]))
        [('s0', 'frames'), ('s1', 'lr')]
    """
    out = set()
    for override in overrides:
        key = override.split("=", 1)[0].lstrip("+~")
        parts = key.split(".")
        if len(parts) >= 4 and parts[:2] == ["task", "stages"] and "@" not in key:
            out.add((parts[2], parts[3]))
    return out


def targets(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``(dotted key, value)`` of every ``_target_`` under ``node`` (plain mappings and lists).

    Examples:
        >>> list(targets({"task": {"env": {"_target_": "a.B", "fn": {"_target_": "a.f"}}}}))
        [('task.env._target_', 'a.B'), ('task.env.fn._target_', 'a.f')]
    """
    if isinstance(node, dict):
        for key, item in node.items():
            path = f"{prefix}.{key}" if prefix else str(key)
            if key == "_target_":
                yield path, item
            else:
                yield from targets(item, path)
    elif isinstance(node, list):
        for index, item in enumerate(node):
            yield from targets(item, f"{prefix}.{index}")
