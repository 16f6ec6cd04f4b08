"""Bring your own env: a gymnasium env registered here (``line_env.LineWorld-v0``) and a batched
TorchRL env train end to end from the CLI with their own keys plus at most two overrides
(``experiment=smoke`` keeps them to seconds); protocol errors reach the user with the fix.

The CLI commands start together when the module's first test runs; each test waits for its own.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
from pathlib import Path

import gymnasium
import pytest
import torch
from drift_env import drift_stage
from helpers import Launched, assert_figure
from line_env import line_stage, unbatched_line
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.envs import GymWrapper, TransformedEnv

from torchrl_stages import GymStageEnv, StagedTask, StageTrainer
from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.collector import StageCollector
from torchrl_stages.config import ConfigError
from torchrl_stages.evaluate import evaluate_policy
from torchrl_stages.gym_env import SuccessKeyError, SuccessReader
from torchrl_stages.learners.dqn import DQNConfig, DQNLearner
from torchrl_stages.metrics import MetricsLog
from torchrl_stages.runs.experiment import build_task
from torchrl_stages.transforms import StageTransform

TESTS = Path(__file__).resolve().parent
TIMEOUT_S = 300
LINE = ["task.env.env_id=line_env:LineWorld-v0", "task.env.stage_fn._target_=line_env.line_stage"]
COMMANDS = {
    # no stage starts: the joint schedule from the task's own starts
    "joint": ["task=gym", "task.stage_starts=false", "schedule=joint", *LINE],
    # the env takes start_stage: stage-k starts, backward schedule
    "backward": ["task=gym", *LINE],
    # a batched TorchRL env of one's own (the grid world stands in for it)
    "custom": [
        "task=custom",
        "task.env._target_=torchrl_stages.envs.GridWorldEnv",
        "+task.env.size=10",
        "+task.env.num_stages=2",
    ],
    # a success key the env does not report: stopped with the key and the fix
    "bad_success_key": ["task=gym", *LINE, "+task.env.pit=true", "task.env.success_key=is_succes"],
    # a factory that ignores batch_size: refused before training, with the fix
    "unbatched": [
        "task=custom",
        "task.stage_starts=false",
        "schedule=joint",
        "task.env._target_=line_env.unbatched_line",
    ],
}


@pytest.fixture(scope="module")
def cli(tmp_path_factory):
    root = tmp_path_factory.mktemp("byoe")
    path = os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])
    launched = {}
    for name, args in COMMANDS.items():
        argv = ["stages-train", *args, "experiment=smoke", "eval.episodes=8"]
        argv.append(f"hydra.run.dir={root / name}")
        launched[name] = Launched(argv, root, TIMEOUT_S, PYTHONPATH=path)

    def result(name: str) -> tuple[int, str, str, Path]:
        done = launched[name].result()
        return done.returncode, done.stdout, done.stderr, root / name

    yield result
    for command in launched.values():
        command.stop()


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.parametrize("name", ["joint", "backward"])
def test_gymnasium_env_trains_from_the_cli(cli, name):
    code, out, err, run_dir = cli(name)
    assert code == 0, (out + err)[-4000:]
    assert "task gym: success" in out and "Traceback" not in err
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["training"]["schedule"] == name
    assert result["episodes"] == 8 and 0.0 <= result["success_rate"] <= 1.0
    assert [s["frames"] > 0 for s in result["training"]["stages"]] == [True, True]
    assert (run_dir / "stage_0.pt").is_file() and (run_dir / "stage_1.pt").is_file()
    saved = OmegaConf.load(run_dir / "config.yaml")
    assert saved.task.env.stage_fn._target_ == "line_env.line_stage"
    assert_figure(run_dir / "learning_curves.png")


def test_torchrl_env_of_ones_own_trains_from_the_cli(cli):
    code, out, err, run_dir = cli("custom")
    assert code == 0, (out + err)[-4000:]
    assert "task custom: success" in out
    assert (run_dir / "stage_1.pt").is_file() and (run_dir / "eval.json").is_file()


def test_unbatched_env_is_refused_with_the_fix(cli):
    code, out, err, run_dir = cli("unbatched")
    assert code == 2, (out + err)[-4000:]
    assert "invalid config: task.env._target_='line_env.unbatched_line'" in err
    assert "batch_size=[]" in err and "Fix:" in err and "Traceback" not in err
    assert not (run_dir / "metrics.csv").exists()


def test_a_success_key_the_env_does_not_report_stops_the_run_with_the_fix(cli):
    code, out, err, run_dir = cli("bad_success_key")
    assert code == 1, (out + err)[-4000:]
    assert "task.env.success_key='is_succes'" in err and "Fix: set" in err
    assert "Traceback" not in err


# ------------------------------------------------------------------ in-process
def test_gym_stage_env_follows_the_task_protocol():
    env = GymStageEnv("LineWorld-v0", "line_env.line_stage", batch_size=(3,), start_stage=1)
    assert env.num_stages == 2 and env.max_steps == 20  # read from the gymnasium env
    td = env.reset()
    assert env.batch_size == torch.Size([3])
    assert (env.stage_fn(td) == 1).all()  # started inside stage 1
    assert env.stage_fn(td).dtype == torch.int64 and env.stage_fn(td).shape == (3, 1)
    assert getattr(env, "start_states", None) is None  # optional hooks it does not offer


@pytest.mark.parametrize("vectorize", ["sync", "async"])
def test_the_copies_step_as_one_vector_env_and_restart_inside_their_stage(vectorize):
    env = GymStageEnv(
        "LineWorld-v0", line_stage, vectorize=vectorize, batch_size=(3,), start_stage=1
    )
    try:
        assert isinstance(env._env, gymnasium.vector.VectorEnv)
        td = env.reset()
        done = 0
        for _ in range(6):  # always right: every copy reaches x = 1 within 4 steps
            td["action"] = torch.ones(3, dtype=torch.int64)
            out, td = env.step_and_maybe_reset(td)
            done += int(out["next", "done"].sum())
            assert (env.stage_fn(td) == 1).all()  # the finished copies restarted in stage 1
        assert done >= 3
    finally:
        env.close()


def test_vectorize_takes_sync_or_async():
    with pytest.raises(ValueError, match=r"vectorize='threads'.*Fix: task.env.vectorize=sync"):
        GymStageEnv("LineWorld-v0", line_stage, vectorize="threads", batch_size=(2,))


def test_task_template_names_what_is_missing(compose_cfg):
    with pytest.raises(ConfigError, match=r"task\.env\.env_id='\?\?\?'.*Fix: set it"):
        build_task(compose_cfg("task=gym", "schedule=joint"))
    with pytest.raises(ConfigError, match=r"stage_starts=false.*Fix: use schedule=joint"):
        build_task(compose_cfg("task=gym", "task.stage_starts=false", *LINE))
    with pytest.raises(ConfigError, match=r"task\.env\._target_='\?\?\?'"):
        build_task(compose_cfg("task=custom"))


def test_box_actions_under_dqn_name_the_template_fix(compose_cfg):
    cfg = compose_cfg(
        "task=gym",
        "task.stage_starts=false",
        "schedule=joint",
        "task.env.env_id=Pendulum-v1",
        "task.env.stage_fn._target_=torchrl_stages.threshold_stage",
        "+task.env.stage_fn.thresholds=[0.0]",
        "task.env.num_stages=2",
    )
    with pytest.raises(ConfigError, match=r"dqn needs a discrete.*algo@task\.stage_template="):
        build_task(cfg)


def test_env_without_num_stages_is_refused(compose_cfg):
    cfg = compose_cfg(
        "task=custom",
        "task.stage_starts=false",
        "schedule=joint",
        "task.env._target_=torchrl_stages.GymStageEnv",
        "+task.env.env_id=CartPole-v1",
        "+task.env.stage_fn=line_env.line_stage",
    )
    with pytest.raises(ConfigError, match=r"no num_stages attribute. Fix: set task.env.num_stages"):
        build_task(cfg)


def test_stage_trainer_refuses_an_unbatched_env():
    env = unbatched_line()
    batched = GymStageEnv("LineWorld-v0", line_stage, batch_size=(4,))
    task = StagedTask(
        OmegaConf.create(
            {
                "name": "line",
                "stage_starts": False,
                "stages": {"a": {}, "b": {}},
                "env": {
                    "_target_": "torchrl_stages.GymStageEnv",
                    "env_id": "LineWorld-v0",
                    "stage_fn": "line_env.line_stage",
                },
            }
        )
    )
    cfg = OmegaConf.structured(DQNConfig(frames=64, frames_per_batch=16, num_envs=4))
    learner = DQNLearner(cfg, task.specs(0))
    trainer = StageTrainer(0, learner, env, batched, cfg)
    with pytest.raises(ValueError, match=r"one batch dimension \[num_envs\].*SerialEnv"):
        trainer.train()


# ------------------------------------------------------------------ success flags
def _always(action: int) -> TensorDictModule:
    """A policy that always takes ``action`` (0: left, 1: right)."""
    return TensorDictModule(
        lambda obs: torch.full(obs.shape[:-1], action, dtype=torch.int64),
        in_keys=["observation"],
        out_keys=["action"],
    )


@pytest.mark.parametrize("success_key", [None, "is_success"])
def test_a_failure_termination_counts_as_failed_where_the_env_reports_success(success_key):
    env = GymStageEnv(
        "LineWorld-v0", line_stage, batch_size=(3,), pit=True, success_key=success_key
    )
    try:
        left, _ = evaluate_policy(env, _always(0), max_steps=20)  # falls in the pit at once
        right, _ = evaluate_policy(env, _always(1), max_steps=20)  # reaches x = 1
    finally:
        env.close()
    assert left.length.tolist() == [1, 1, 1] and right.length.tolist() == [8, 8, 8]
    assert right.success.all()
    # without the flag every termination is a success, the pit's too
    assert left.success.tolist() == [success_key is None] * 3


def test_leaving_stage_k_is_stage_ks_success_unless_the_task_failed():
    base = GymStageEnv(
        "LineWorld-v0", line_stage, batch_size=(2,), pit=True, success_key="is_success"
    )
    env = TransformedEnv(base, StageTransform(line_stage, 2, train_stage=0, standalone=True))
    try:
        left, _ = evaluate_policy(env, _always(0), max_steps=20)
        right, rollout = evaluate_policy(env, _always(1), max_steps=20)
    finally:
        env.close()
    assert right.length.tolist() == [4, 4]  # x = 0.5 leaves stage 0: its episode ends there
    assert right.success.all() and not rollout["next", "terminated"][:, :3].any()
    assert not left.success.any()  # the pit ends stage 0's episode unsolved


def test_a_success_key_the_env_never_reports_is_refused():
    def ended(*done: bool) -> TensorDict:  # a step's output: the env's own done
        return TensorDict(done=torch.tensor(done).unsqueeze(-1), batch_size=[len(done)])

    reader = SuccessReader("is_succes", batch_size=(2,), patience=3)
    td = reader({"is_succes": [True, False]}, ended(True, True))
    assert td["success"].squeeze(-1).tolist() == [True, False]
    for _ in range(5):  # reported once: later episodes without it read False
        assert not reader({}, ended(True, True))["success"].any()
    never = SuccessReader("is_succes", batch_size=(2,), patience=3)
    for _ in range(5):  # resets and steps that end no episode do not count
        never({}, TensorDict(batch_size=[2]))
        never({}, ended(False, False))
    never({}, ended(True, False))
    never({}, ended(False, True))
    with pytest.raises(SuccessKeyError, match=r"task\.env\.success_key='is_succes'.*Fix: set"):
        never({}, ended(True, False))


class _OnlyAtTheEnd(gymnasium.Wrapper):
    """Reports ``is_success`` on an episode's last step only (as Stable-Baselines3 asks)."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if not (terminated or truncated):
            info.pop("is_success", None)
        return obs, reward, terminated, truncated, info


def test_a_stage_whose_episodes_leave_it_needs_no_report_of_the_key():
    """Stage 0's episodes end where they leave stage 0, where the env's own episode goes on:
    the key is never reported, and that is no error."""
    base = GymStageEnv(
        "LineWorld-v0",
        line_stage,
        batch_size=(2,),
        pit=True,
        success_key="is_success",
        wrappers=[_OnlyAtTheEnd],
        start_stage=0,
    )
    env = TransformedEnv(base, StageTransform(line_stage, 2, train_stage=0, standalone=True))
    try:
        td, policy, ended, solved = env.reset(), _always(1), 0, 0
        for _ in range(600):  # 1 to 4 steps each: 300 stage-0 episodes or more
            out, td = env.step_and_maybe_reset(policy(td))
            done = out["next", "done"]
            ended += int(done.sum())
            solved += int(out["next", "success"][done].sum())
        assert ended >= 300 and solved == ended
    finally:
        env.close()


def test_training_episodes_count_the_flag():
    done = torch.tensor([[True, True]]).unsqueeze(-1)
    batch = TensorDict(
        {
            "next": {
                "done": done,
                "terminated": done,
                "success": torch.tensor([[[True], [False]]]),
                "episode_reward": torch.zeros(1, 2, 1),
            }
        },
        [1, 2],
    )
    assert MetricsLog.episodes_by_row(batch)[0]["episode_success"] == 0.5


def test_the_gym_template_passes_the_success_key(compose_cfg):
    cfg = compose_cfg("task=gym", *LINE, "+task.env.pit=true", "task.env.success_key=is_success")
    task = build_task(cfg)
    env = task.base_env(2)
    try:
        assert env.observation_spec["success"].dtype == torch.bool
    finally:
        env.close()
    assert task.specs(0).observation_keys == ["observation"]  # the flag is no input


# ------------------------------------------------------------------ resume
def _drift(vectorize: str = "sync", **kwargs) -> GymStageEnv:
    """Four copies of ``Drift-v0`` inside stage 1, seeded as a run seeds them."""
    env = GymStageEnv(
        "drift_env:Drift-v0",
        drift_stage,
        vectorize=vectorize,
        batch_size=(4,),
        start_stage=1,
        **kwargs,
    )
    env.set_seed(3)
    return env


def _collector(env: GymStageEnv) -> StageCollector:
    """Four batches of 64 steps per copy, all copies staying put (the drift is their noise)."""
    return StageCollector(env, _always(1), frames_per_batch=256, total_frames=4 * 256)


@pytest.mark.parametrize("vectorize", ["sync", pytest.param("async", marks=pytest.mark.slow)])
def test_a_checkpointed_collector_continues_the_same_episodes_bitwise(vectorize, tmp_path):
    """Episodes of 200 random steps, checkpointed 128 steps in (tensors and JSON on disk): the
    resumed collector rebuilds each copy's episode (its np_random, its TimeLimit count) and
    goes on as if it had never stopped."""
    env = _drift(vectorize)
    try:
        whole = list(_collector(env))
    finally:
        env.close()
    checkpoints = StageCheckpoints(tmp_path, every=0)
    env = _drift(vectorize)
    try:
        collector = _collector(env)
        first = list(itertools.islice(collector, 2))
        path = checkpoints.save(collector.frames, {"collector": collector})
    finally:
        env.close()
    resumed = _drift(vectorize)
    try:
        collector = _collector(resumed)
        checkpoints.load(path, {"collector": collector})
        rest = list(collector)
    finally:
        resumed.close()
    assert resumed.episodes_rebuilt
    assert not torch.cat(whole[:2], 1)["next", "done"].any()  # one episode per copy so far
    assert whole[3]["next", "truncated"].any()  # step 200 of the rebuilt episodes truncates
    assert len(first + rest) == len(whole) == 4
    for a, b in zip(whole, first + rest, strict=True):
        assert (a == b).all()


def _warnings(caplog, words: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if words in r.getMessage()]


def test_an_env_that_draws_from_elsewhere_warns_once_and_starts_its_episodes_over(tmp_path, caplog):
    """Steps drawn from a generator of the env's own: the replayed episodes differ, so one line
    per resume (for the training and the evaluation env together) says they start over, and
    they do, from the resets the saved np_random gives."""
    checkpoints = StageCheckpoints(tmp_path, every=0)
    env, eval_env = _drift(entropy=True), _drift(entropy=True)
    try:
        collector = _collector(env)
        next(iter(collector))
        eval_env.rollout(3)
        path = checkpoints.save(collector.frames, {"collector": collector, "eval_env": eval_env})
        fresh_starts = env.reset()["observation"]  # what the saved np_random draws next
    finally:
        env.close()
        eval_env.close()
    for resume in (1, 2):  # two resumes in one process (a sweep's jobs): a line each
        resumed, resumed_eval = _drift(entropy=True), _drift(entropy=True)
        try:
            collector = _collector(resumed)
            with caplog.at_level(logging.WARNING, logger="torchrl_stages"):
                checkpoints.load(path, {"collector": collector, "eval_env": resumed_eval})
            batch = next(iter(collector))
        finally:
            resumed.close()
            resumed_eval.close()
        assert len(_warnings(caplog, "did not rebuild")) == resume
        assert not resumed.episodes_rebuilt and not resumed_eval.episodes_rebuilt
        assert collector.frames == 512
        assert torch.equal(batch["observation"][:, 0], fresh_starts)
    line = _warnings(caplog, "did not rebuild")[0]
    assert "gymnasium env 'drift_env:Drift-v0'" in line and "4 of 4 copies" in line
    assert "copy 0: the replayed observation differs from the saved one" in line
    assert "they start over" in line and "not bitwise equal" in line and "\n" not in line


def test_an_env_without_state_says_its_episodes_start_over(tmp_path, caplog):
    """A TorchRL env that keeps no state in ``state_dict`` (torchrl's own ``GymWrapper``)."""
    checkpoints = StageCheckpoints(tmp_path, every=0)
    vector = gymnasium.vector.SyncVectorEnv(
        [lambda: gymnasium.make("LineWorld-v0")] * 2,
        autoreset_mode=gymnasium.vector.AutoresetMode.DISABLED,
    )
    env = GymWrapper(vector, categorical_action_encoding=True)
    try:
        collector = StageCollector(env, _always(1), frames_per_batch=8, total_frames=16)
        next(iter(collector))
        path = checkpoints.save(collector.frames, {"collector": collector})
        with caplog.at_level(logging.WARNING, logger="torchrl_stages"):
            checkpoints.load(path, {"collector": collector})
    finally:
        env.close()
    (line,) = _warnings(caplog, "holds no state of the env")
    assert "env GymWrapper (it keeps none in state_dict" in line and "episodes start over" in line


def test_a_checkpoint_without_the_episodes_warns_and_starts_them_over(caplog):
    """A collector's and an env's state written before the copies' episodes were kept (the
    state a ``GymStageEnv`` had none of): a warning each, no failure."""
    env = _drift()
    try:
        collector = _collector(env)
        with caplog.at_level(logging.WARNING, logger="torchrl_stages"):
            collector.load_state_dict({"frames": 256})
            env.load_state_dict({})
        batch = next(iter(collector))
    finally:
        env.close()
    (line,) = _warnings(caplog, "holds no state of the env")
    assert "env GymStageEnv (written by a version that did not keep it)" in line
    (line,) = _warnings(caplog, "did not rebuild")
    assert "the checkpoint holds none of its episodes" in line and "start over" in line
    assert not env.episodes_rebuilt and collector.frames == 512 and batch.shape == (4, 64)
