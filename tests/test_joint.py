"""The joint schedule (the paper's Algorithm 1) and the flat baseline, on tiny grid worlds."""

from __future__ import annotations

import io
import logging
import sys

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from torchrl_stages.envs import GridWorldEnv
from torchrl_stages.learners.dqn import DQNConfig
from torchrl_stages.loop import Stopwatch
from torchrl_stages.schedules import JointTrainer, train_flat
from torchrl_stages.schedules.joint import JointCounters
from torchrl_stages.task import StagedTask

TINY = dict(
    frames=512,
    frames_per_batch=128,
    num_envs=16,
    init_random_frames=128,
    batch_size=32,
    eval_every=256,
    eval_episodes=8,
    gamma=0.9,
)


def grid_task(stages: int = 2, **task) -> StagedTask:
    cfg = OmegaConf.structured(DQNConfig(**TINY))
    return StagedTask(
        OmegaConf.create(
            {
                "name": "grid",
                "stages": {f"s{k}": cfg for k in range(stages)},
                "env": {
                    "_target_": "torchrl_stages.envs.GridWorldEnv",
                    "size": 5 * stages,
                    "num_stages": stages,
                },
                **task,
            }
        )
    )


def transitions(stages: list[int], next_stages: list[int]) -> TensorDict:
    """Hand-made stored transitions of the 10 x 10 two-stage grid (column = 5 * stage)."""
    n = len(stages)
    stage = torch.tensor(stages).unsqueeze(-1)
    nxt = torch.tensor(next_stages).unsqueeze(-1)
    cells = torch.stack([torch.arange(n), 5 * stage.squeeze(-1) + 4 * (nxt == stage).squeeze(-1)])
    no = torch.zeros(n, 1, dtype=torch.bool)
    return TensorDict(
        observation=cells.T.float() / 5,
        action=torch.full((n,), 3),
        stage=stage,
        next=TensorDict(
            observation=torch.stack([torch.arange(n), 5 * nxt.squeeze(-1)], -1).float() / 5,
            stage=nxt,
            stage_transition=nxt > stage,
            reward=torch.zeros(n, 1),
            terminated=no,
            truncated=no.clone(),
            done=no.clone(),
            batch_size=[n],
        ),
        batch_size=[n],
    )


def _counters(trainer: JointTrainer) -> JointCounters:
    return JointCounters(trainer.task.num_stages, trainer.n)


def test_each_transition_goes_to_the_buffer_of_the_stage_of_s_t():
    trainer = JointTrainer(grid_task())
    counters = _counters(trainer)
    trainer._route(transitions([0, 0, 1, 0, 1], [0, 1, 1, 1, 1]).unsqueeze(0), [0], counters)
    assert counters.stored == [[3, 2]]
    assert trainer.buffers[0].held()["stage"].flatten().tolist() == [0, 0, 0]
    assert trainer.buffers[1].held()["stage"].flatten().tolist() == [1, 1]


def test_sampled_transition_reward_follows_the_next_learner_after_storage():
    trainer = JointTrainer(grid_task())
    trainer._route(transitions([0, 0], [1, 0]).unsqueeze(0), [0], _counters(trainer))
    transform, next_learner = trainer.transforms[0], trainer.learners[1]
    stored = trainer.buffers[0].held()[0]

    def buffer_all():  # the stored transitions as a sample reads them
        return transform(stored.clone())

    first = buffer_all()
    v1 = next_learner.value()(first["next"].select("observation").clone())["state_value"]
    assert first["next", "reward"][0].item() == pytest.approx(0.9 * v1[0].item(), rel=1e-5)
    assert first["next", "terminated"].flatten().tolist() == [True, False]
    with torch.no_grad():  # stage 1 keeps learning after the data was stored
        for p in next_learner.loss.target_value_network_params.values(True, True):
            p.add_(0.5)
    second = buffer_all()
    v1_new = next_learner.value()(first["next"].select("observation").clone())["state_value"]
    assert second["next", "reward"][0].item() == pytest.approx(0.9 * v1_new[0].item(), rel=1e-5)
    assert second["next", "reward"][0] != first["next", "reward"][0]
    assert second["next", "reward"][1].item() == 0.0  # no transition: the raw reward
    assert stored["next", "reward"].flatten().tolist() == [0.0, 0.0]


def test_every_stage_updates_in_one_iteration_last_stage_first(monkeypatch):
    task = grid_task(stages=3)
    trainer = JointTrainer(task)
    counters = _counters(trainer)
    for _ in range(7):  # past init_random_frames (128) in every buffer
        trainer._route(transitions([0, 1, 2] * 20, [0, 1, 2] * 20).unsqueeze(0), [0], counters)
    calls = []
    for m, learner in enumerate(trainer.learners):
        monkeypatch.setattr(learner, "update", lambda batch, m=m: calls.append(m) or {})
    trainer._update([0], counters, Stopwatch())
    per_batch = int(task.stage_cfg(0).updates_per_batch)
    assert calls == [2] * per_batch + [1] * per_batch + [0] * per_batch


def test_joint_schedule_runs_every_phase_and_updates_every_stage():
    [run] = JointTrainer(grid_task()).train()
    results, phases = run.results, run.extra["phases"]
    assert [p["start_stage"] for p in phases] == [1, 0]
    assert all(r.updates > 0 for r in results)
    assert results[1].frames > results[0].frames  # stage 1 also gets phase 0's episodes
    # every stage reports the last phase's evaluation (its whole-task episodes)
    assert phases[-1]["discounted_return"] is not None
    assert all(r.discounted_return == phases[-1]["discounted_return"] for r in results)


def test_away_from_a_terminal_each_phase_logs_its_evaluations(monkeypatch, caplog):
    monkeypatch.setattr(sys, "stderr", io.StringIO())  # not a terminal: lines, not a bar
    caplog.set_level(logging.INFO, logger="torchrl_stages")
    JointTrainer(grid_task(), progress=True).train()
    lines = [r.getMessage() for r in caplog.records if r.name == "torchrl_stages"]
    shown = [line.split(", success")[0] for line in lines]
    assert shown == [
        "the joint phase from stage 1 (s1): 256 of 512 frames",
        "the joint phase from stage 1 (s1): 512 of 512 frames",
        "the joint phase from stage 0 (s0): 256 of 512 frames",
        "the joint phase from stage 0 (s0): 512 of 512 frames",
    ]
    assert all(", value error " in line and line.endswith("s") for line in lines)


class StartlessGrid(GridWorldEnv):
    """A grid world that can only start at the task's own starts (no start_stage)."""

    def __init__(self, batch_size=(), **kwargs):
        super().__init__(batch_size, **kwargs)


@pytest.mark.slow
def test_joint_schedule_trains_an_env_without_stage_starts():
    task = grid_task(stage_starts=False)
    for stage in task.cfg.stages.values():  # whole-task episodes must reach stage 1
        stage.frames = 2048
    task.cfg.env._target_ = f"{__name__}.StartlessGrid"
    task = StagedTask(task.cfg)
    trainer = JointTrainer(task)
    assert trainer.starts == [None]  # one phase from the whole-task starts
    [run] = trainer.train()
    results, phases = run.results, run.extra["phases"]
    assert len(phases) == 1 and phases[0]["start_stage"] is None
    assert all(r.updates > 0 for r in results)
    with pytest.raises(ValueError, match="stage_starts=false"):
        task.stage_env(1, 4)


def test_flat_learner_discounts_each_transition_with_its_stage_gamma():
    task = grid_task()
    task.cfg.stages.s1.gamma = 0.99
    [run] = train_flat(task)
    learners, results = run.learners, run.results
    assert learners[0] is learners[1] and len(results) == 1
    batch = transitions([0, 1], [0, 1])
    batch.set("steps_to_next_obs", torch.ones(2, 1))
    plain = learners[0].loss.value_estimator.value_estimate(batch.clone())
    from torchrl_stages.transforms import StageDiscount

    discounted = StageDiscount([0.9, 0.99], gamma=0.9)(batch.clone())
    target = learners[0].loss.value_estimator.value_estimate(discounted)
    assert target[0].item() == pytest.approx(plain[0].item())  # stage 0: gamma 0.9
    assert target[1].item() == pytest.approx(plain[1].item() * 0.99 / 0.9, rel=1e-5)
