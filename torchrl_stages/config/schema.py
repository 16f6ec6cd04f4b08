"""The config dataclasses, each field with its bound; ``conf/`` YAML files override them."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field, is_dataclass
from typing import Any

from omegaconf import II, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_stages.config.bounds import bound, flag, free, in_range, non_negative, one_of, positive

LOGGER_BACKENDS = ("csv", "tensorboard", "wandb", "mlflow", "none")


@dataclass
class StageConfig:
    """Hyper-parameters shared by every stage learner; budgets count env frames."""

    algo: str = free()  # a registered algorithm (torchrl_stages.learners.ALGORITHMS)
    # a Learner subclass with the keys of `algo`: {_target_: my_pkg.MyLearner, my_key: 1}
    learner: dict[str, Any] = free(factory=dict)
    gamma: float = in_range(0, 1, 0.99, low_open=True)  # this stage's discount
    lr: float = positive(1e-3)  # learning rate (the critic's, for actor-critic algorithms)
    # every learning rate decays linearly to this fraction of its start over `frames`
    lr_end_factor: float = in_range(0, 1, 1.0)
    max_grad_norm: float | None = positive(None)  # clip each optimizer's gradient norm (null: off)
    # torch.optim.Adam(fused=True): the same update up to rounding, cheaper for small networks
    fused_adam: bool = flag(False)
    num_cells: list[int] = positive(factory=lambda: [64, 64])  # hidden layers of each MLP
    fourier_features: int = non_negative(0)  # octaves of sin/cos input encoding (0: raw input)
    # CNN over image observations (C, H, W), one entry per conv layer, before the MLP
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
    # greedy episodes per evaluation (or every start state the env enumerates)
    eval_episodes: int = positive(64)
    eval_max_steps: int | None = positive(None)  # longer greedy episodes fail (null: env limit)
    success_threshold: float | None = in_range(0, 1, None)  # early stop at this success (null: off)
    # ... and |V(s_0) - discounted greedy return| <= this (null: not checked)
    value_tolerance: float | None = non_negative(None)
    value_error_reduce: str = one_of("mean", "max", default="mean")  # over the start states
    patience: int = positive(1)  # consecutive evaluations that must meet the early stop
    min_frames: int = non_negative(0)  # no early stop before this many frames
    keep_best: bool = flag(True)  # budget exhausted: restore the best evaluated weights
    # "best": highest success, then lowest value_error | highest mean discounted return
    keep_best_by: str = one_of("value_error", "return", default="value_error")


@dataclass
class TaskConfig:
    """A multi-stage task: its env and one learner config per stage, in stage order."""

    name: str = free()
    # keyword arguments of the multi-stage env, `_target_` its class
    env: dict[str, Any] = free(factory=dict)
    eval_env: dict[str, Any] = free(factory=dict)  # over `env` in the whole-task evaluation
    stages: dict[str, Any] = free(factory=dict)
    # stages s0..s<N-1> (N: the env's num_stages), each this with its own keys over it
    stage_template: dict[str, Any] = free(factory=dict)
    eval_episodes: int = positive(100)  # this task's default for eval.episodes
    threads: int = positive(1)  # this task's default for `threads` (docs/speed.md)
    # whether the env can start an episode in a chosen stage (else only schedule=joint)
    stage_starts: bool = flag(True)


@dataclass
class ScheduleConfig:
    """How the stages are trained: ``backward``, ``joint`` or ``flat`` (one learner)."""

    name: str = free("backward")  # a registered schedule (get_schedule names them)


@dataclass
class LoggerConfig:
    """Where metrics go, through ``torchrl.record.loggers.get_logger``."""

    backend: str = one_of(*LOGGER_BACKENDS, default="csv")
    exp_name: str = free("${task.name}")
    project: str = free("torchrl-stages")  # wandb project / mlflow experiment


@dataclass
class EvalConfig:
    """Whole-task evaluation of the stacked greedy policy after training."""

    episodes: int = positive(II("task.eval_episodes"))  # default: the task's
    plots: bool = flag(True)
    # log eval/task/{success_rate, seconds} at every evaluation of the first stage or phase
    probe: bool = flag(False)


@dataclass
class ObjectiveConfig:
    """The entry of ``eval.json`` a run is judged by, and whether higher is better."""

    metric: str = one_of("success_rate", "mean_return", "mean_steps", default="success_rate")
    direction: str = one_of("maximize", "minimize", default="maximize")


@dataclass
class TuneConfig:
    """The ``tune`` block of ``stages-tune``: an Optuna study of ``objective`` over ``params``,
    each a range ``{low: 1e-4, high: 1e-2, log: true}`` or ``{choices: [dqn, sac]}``."""

    study_name: str = free("${task.name}")
    # Optuna storage: an RDB URL (sqlite:///study.db) or a journal file (study.log, for NFS)
    storage: str = free("sqlite:///study.db")
    n_trials: int = positive(20)  # trials this command runs (a rerun adds as many to the study)
    sampler: str = one_of("tpe", "random", default="tpe")
    seed: int = non_negative(II("seed"))  # plus the number of trials already in the study
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
    # several seeds in one process, networks stacked, run directories seed_<s>/ (null: `seed`)
    seeds: list[int] | None = non_negative(None)
    # cpu | cuda | cuda:<index> | mps
    device: str = bound(
        "cpu", pattern=r"cpu|mps|cuda(:\d+)?", text="cpu, cuda, cuda:<index> or mps"
    )
    # torch intra-op threads (default: task.threads); 1 per job when jobs share the cores
    threads: int = positive(II("task.threads"))
    progress: bool = flag(True)  # tqdm bar per stage (hidden anyway when stderr is not a TTY)
    checkpoint_every: int = non_negative(50_000)  # frames between checkpoints (0: none)
    checkpoint_keep: int = positive(2)  # newest checkpoints kept per stage
    # torch.compile of every learner's loss (auto: off on CPU, reduce-overhead on a GPU)
    compile: str = one_of(
        "auto", "off", "default", "reduce-overhead", "max-autotune", default="auto"
    )
    resume: bool = flag(False)  # continue the run in hydra.run.dir (same overrides otherwise)
    # a directory of finished stages shared by runs (schedule=backward; see `stages-store`)
    stage_store: str | None = free(None)
    # a run directory whose unchanged finished stages are reused (schedule=backward)
    init_from: str | None = free(None)
    overwrite: bool = flag(False)  # replace the run in hydra.run.dir
    # keys set in every stage, but not over one set for a stage on the command line
    all_stages: dict[str, Any] = free(factory=dict)


@dataclass
class TuneAppConfig(TrainConfig):
    """Root config of ``stages-tune``: that of ``stages-train`` and the ``tune`` block."""

    tune: TuneConfig = field(default_factory=TuneConfig)


def as_dataclass(cfg: Any) -> Any:
    """A structured config node as its dataclass (reads ~1000x faster); anything else as is."""
    if isinstance(cfg, DictConfig) and is_dataclass(OmegaConf.get_type(cfg)):
        with contextlib.suppress(OmegaConfBaseException):  # e.g. missing: the node raises on read
            return OmegaConf.to_object(cfg)
    return cfg
