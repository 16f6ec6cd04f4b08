"""The stage loop (``StageTrainer.train``) with a scripted learner, and the backward schedule."""

from __future__ import annotations

import dataclasses
import io
import logging
import sys
from types import SimpleNamespace

import pytest
import torch
from helpers import two_stage_grid
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl_stages.early_stop import Evaluation
from torchrl_stages.learners import Learner
from torchrl_stages.learners.ddpg import DDPGLearner
from torchrl_stages.learners.dqn import DQNConfig, DQNLearner
from torchrl_stages.learners.td3 import TD3Learner
from torchrl_stages.schedules import train_backward, train_stage
from torchrl_stages.stage import StageTrainer
from torchrl_stages.task import StagedTask
from torchrl_stages.transforms import StageTransform
from torchrl_stages.values import QMaxValue, with_params

SIZE, NUM_ENVS = 10, 16


def _task(stage=None) -> StagedTask:
    stage = stage if stage is not None else DQNConfig(gamma=0.9)
    return two_stage_grid(stage, size=SIZE)


def _cfg(**kw) -> DQNConfig:
    base = {"frames_per_batch": 128, "num_envs": NUM_ENVS, "batch_size": 32, "eval_every": 0}
    return OmegaConf.structured(DQNConfig(**{**base, **kw}))


class FakeLearner(Learner):
    """A scripted right-then-down policy; each update adds 1 to ``weight`` and is recorded."""

    algo = "fake"

    def __init__(self, cfg, specs) -> None:
        super().__init__(cfg, specs)
        self.weight = nn.Parameter(torch.zeros(()))
        self.policy = TensorDictModule(self._act, ["observation"], ["action"])
        self.exploration_policy = self.policy
        self.loss = SimpleNamespace(
            in_keys=[
                "observation",
                "action",
                ("next", "observation"),
                ("next", "reward"),
                ("next", "done"),
                ("next", "terminated"),
            ]
        )
        self.annealed: list[int] = []  # frames passed to anneal_exploration, in order
        self.update_frames: list[int] = []  # frames collected when each update happened
        self.batch_sizes: list[int] = []
        self.policy_frames: list[int] = []  # frames collected when the policy acted

    def _act(self, obs: torch.Tensor) -> torch.Tensor:
        self.policy_frames.append(self.annealed[-1] if self.annealed else 0)
        col = torch.round(obs[..., 1] * 5).long()
        return torch.where(col < SIZE - 1, 3, 1)

    def update(self, batch):
        self.update_frames.append(self.annealed[-1])
        self.batch_sizes.append(batch.numel())
        with torch.no_grad():
            self.weight.add_(1.0)
        self.num_updates += 1
        return {"loss": torch.zeros(())}

    def anneal_exploration(self, frames: int) -> None:
        self.annealed.append(frames)

    def value(self, live: bool = False):
        weight = self.weight.detach() if live else self.weight.detach().clone()
        return TensorDictModule(
            lambda obs: weight.expand(*obs.shape[:-1], 1), ["observation"], ["state_value"]
        )


def _trainer(cfg, stage: int = 1) -> tuple[StageTrainer, FakeLearner]:
    task = _task()
    learner = FakeLearner(cfg, task.specs(stage))
    env = task.stage_env(stage, cfg.num_envs)
    env.set_seed(0)
    trainer = StageTrainer(stage, learner, env, task.stage_eval_env(stage), cfg)
    return trainer, learner


def _script(trainer: StageTrainer, learner: FakeLearner, evals, monkeypatch) -> list[dict]:
    """Replaces ``trainer.evaluate`` by a scripted sequence of (success, value error, return);
    returns the log of calls (frames and the weight at the time)."""
    calls: list[dict] = []
    it = iter(evals)

    def evaluate(frames: int, active=None) -> Evaluation:
        calls.append({"frames": frames, "weight": learner.weight.item()})
        success, value_error, ret = next(it)
        return Evaluation([success], [value_error], [ret], [frames], [learner.num_updates])

    monkeypatch.setattr(trainer, "evaluate", evaluate)
    return calls


def test_no_update_before_init_random_frames():
    cfg = _cfg(frames=1024, init_random_frames=256, updates_per_batch=3)
    trainer, learner = _trainer(cfg)
    [(_, result)] = trainer.train()
    batches = list(range(128, 1024 + 1, 128))
    assert learner.annealed == batches
    assert result.frames == 1024
    learning = [f for f in batches if f >= 256]
    assert learner.update_frames == [f for f in learning for _ in range(3)]
    assert result.updates == learner.num_updates == 3 * len(learning) == 21
    assert learner.weight.item() == 21.0
    assert learner.batch_sizes == [cfg.batch_size] * 21
    # random actions for the first 256 frames, the policy from then on
    steps_per_batch = 128 // NUM_ENVS
    assert min(learner.policy_frames) == 256
    assert len(learner.policy_frames) == steps_per_batch * (len(batches) - 2)
    assert not result.early_stopped and not result.restored_best
    assert result.success_rate is None and result.value_error is None


class RecordingLearner(FakeLearner):
    """Keeps a copy of every minibatch it is given."""

    def update(self, batch):
        self.batches = [*getattr(self, "batches", []), batch.clone()]
        return super().update(batch)


class RandomUpdateLearner(RecordingLearner):
    """An update that draws from torch's generator (as TD3's target smoothing does)."""

    update_draws_random = True

    def update(self, batch):
        torch.randn(3)
        return super().update(batch)


def _minibatches(cls, cfg, per_update: bool) -> list:
    task = _task()
    learner = cls(cfg, task.specs(1))
    learner.update_draws_random = per_update  # True: a buffer draw right before every update
    env = task.stage_env(1, cfg.num_envs)
    env.set_seed(0)
    torch.manual_seed(0)
    StageTrainer(1, learner, env, task.stage_eval_env(1), cfg).train()
    return learner.batches


def _same(a: list, b: list) -> bool:
    pairs = zip(a, b, strict=False)
    return len(a) == len(b) and all(bool((x == y).all()) for x, y in pairs)


def test_one_draw_per_batch_gives_the_minibatches_of_a_draw_per_update():
    """The loop samples a batch's ``updates_per_batch`` minibatches in one draw: the same
    minibatches, in the same order, as a draw before each update."""
    cfg = _cfg(frames=768, init_random_frames=256, updates_per_batch=4)
    one_draw = _minibatches(RecordingLearner, cfg, per_update=False)
    reference = _minibatches(RecordingLearner, cfg, per_update=True)
    assert len(one_draw) == 5 * 4  # batches at 256, 384, ..., 768 frames
    assert all(b.batch_size == (cfg.batch_size,) for b in one_draw)
    assert _same(one_draw, reference)
    for a, b in zip(one_draw, reference, strict=True):
        assert torch.equal(a["next", "observation"], b["next", "observation"])
    assert len({tuple(b["observation"].flatten().tolist()) for b in one_draw}) == len(one_draw)


def test_one_draw_per_batch_would_change_the_minibatches_of_an_update_that_draws():
    """Where the update draws random numbers (TD3), one draw per batch would give other
    minibatches than a draw per update; such learners declare ``update_draws_random`` and the
    loop then draws per update (``test_only_td3_updates_draw_random_numbers`` checks the
    declarations against the learners' updates)."""
    cfg = _cfg(frames=768, init_random_frames=256, updates_per_batch=4)
    assert TD3Learner.update_draws_random and not DQNLearner.update_draws_random
    assert not DDPGLearner.update_draws_random
    assert RandomUpdateLearner(cfg, _task().specs(1)).update_draws_random
    declared = _minibatches(RandomUpdateLearner, cfg, per_update=True)
    one_draw = _minibatches(RandomUpdateLearner, cfg, per_update=False)
    assert len(declared) == len(one_draw) == 20
    assert not _same(declared, one_draw)


def test_early_stop_breaks_at_the_evaluation_that_meets_the_criterion(monkeypatch):
    cfg = _cfg(
        frames=2048,
        init_random_frames=128,
        updates_per_batch=2,
        eval_every=128,
        success_threshold=1.0,
        patience=2,
        min_frames=512,
    )
    trainer, learner = _trainer(cfg)
    # evaluations start where they can stop the stage: min_frames - (patience - 1) * eval_every
    evals = [
        (0.5, 0.0, 0.5),  # 384
        (1.0, 0.0, 0.5),  # 512
        (1.0, 0.1, 0.5),  # 640: a streak of 2 after min_frames: stop here
    ] + [(0.0, 1.0, 0.0)] * 20
    calls = _script(trainer, learner, evals, monkeypatch)
    [(_, result)] = trainer.train()
    assert [c["frames"] for c in calls] == [384, 512, 640]
    assert result.frames == 640 and result.early_stopped
    assert not result.restored_best
    assert result.updates == learner.num_updates == 2 * 5
    assert learner.update_frames[-1] == 640  # no update after the stopping evaluation
    assert learner.weight.item() == calls[-1]["weight"] == 10.0
    assert (result.success_rate, result.value_error) == (1.0, 0.1)


def test_value_tolerance_is_part_of_the_early_stop(monkeypatch):
    cfg = _cfg(
        frames=1024,
        init_random_frames=128,
        updates_per_batch=1,
        eval_every=256,
        success_threshold=1.0,
        value_tolerance=0.05,
        patience=1,
    )
    trainer, learner = _trainer(cfg)
    evals = [(1.0, 0.2, 0.0), (1.0, 0.06, 0.0), (1.0, 0.04, 0.0), (1.0, 0.0, 0.0)]
    calls = _script(trainer, learner, evals, monkeypatch)
    [(_, result)] = trainer.train()
    assert [c["frames"] for c in calls] == [256, 512, 768]
    assert result.frames == 768 and result.early_stopped


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _evaluation_lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "torchrl_stages"]


def test_away_from_a_terminal_every_evaluation_logs_a_line(monkeypatch, caplog):
    # nohup, a batch job, CI: no bar, one line per evaluation (Hydra sends it to the console and
    # to the run's log file)
    trainer, learner = _trainer(_cfg(frames=512, init_random_frames=128, eval_every=256))
    trainer.progress = True
    _script(trainer, learner, [(0.5, 0.25, 0.0), (1.0, 0.125, 0.0)], monkeypatch)
    monkeypatch.setattr(sys, "stderr", io.StringIO())  # not a terminal
    caplog.set_level(logging.INFO, logger="torchrl_stages")
    trainer.train()
    lines = _evaluation_lines(caplog)
    assert [line.rsplit(", ", 1)[0] for line in lines] == [
        "stage 1 (1): 256 of 512 frames, success 0.50, value error 0.250",
        "stage 1 (1): 512 of 512 frames, success 1.00, value error 0.125",
    ]
    assert all(line.endswith("s") for line in lines)  # the seconds since the stage started
    assert sys.stderr.getvalue() == ""  # and no bar


def test_on_a_terminal_the_bar_has_no_estimate_when_an_early_stop_can_end_the_stage(
    monkeypatch, caplog
):
    # the budget is where a stage that stops early seldom gets: no percentage or time left
    # counting to it, but the frames, their rate and the budget; no log lines beside the bar
    cfg = _cfg(frames=1024, init_random_frames=128, eval_every=256, success_threshold=1.0)
    trainer, learner = _trainer(cfg)
    trainer.progress = True
    _script(trainer, learner, [(0.5, 0.0, 0.0)] * 4, monkeypatch)
    monkeypatch.setattr(sys, "stderr", _Terminal())
    caplog.set_level(logging.INFO, logger="torchrl_stages")
    trainer.train()
    shown = sys.stderr.getvalue()
    assert "stage 1 (1) (budget 1024 frames): 0frame [" in shown
    assert "%|" not in shown and "/1024" not in shown and "<" not in shown
    assert _evaluation_lines(caplog) == []
    # without an early stop the budget is where the stage ends: the bar counts to it
    trainer, learner = _trainer(_cfg(frames=256, init_random_frames=128, eval_every=256))
    trainer.progress = True
    monkeypatch.setattr(sys, "stderr", _Terminal())
    trainer.train()
    assert "/256 [" in sys.stderr.getvalue()


EVALS = [  # (success, value error, return); the best is the third one
    (0.5, 0.10, 0.0),
    (1.0, 0.20, 0.0),
    (1.0, 0.05, 0.0),
    (0.8, 0.01, 0.0),
    (1.0, 0.10, 0.0),
    (0.9, 0.00, 0.0),
]


def _budget_cfg(**kw):
    return _cfg(
        frames=768,
        init_random_frames=128,
        updates_per_batch=2,
        eval_every=128,
        success_threshold=1.0,
        patience=3,
        **kw,
    )


def test_budget_exhausted_restores_the_best_evaluated_weights(monkeypatch):
    trainer, learner = _trainer(_budget_cfg())
    calls = _script(trainer, learner, EVALS, monkeypatch)
    [(_, result)] = trainer.train()
    assert len(calls) == len(EVALS) and result.frames == 768
    assert not result.early_stopped and result.restored_best
    assert learner.weight.item() == calls[2]["weight"] == 6.0
    assert learner.weight.item() != calls[-1]["weight"]
    assert (result.success_rate, result.value_error) == (1.0, 0.05)
    assert result.updates == 12  # updates done, not those of the restored weights


def test_keep_best_off_keeps_the_last_weights(monkeypatch):
    trainer, learner = _trainer(_budget_cfg(keep_best=False))
    calls = _script(trainer, learner, EVALS, monkeypatch)
    [(_, result)] = trainer.train()
    assert not result.restored_best and not result.early_stopped
    assert learner.weight.item() == calls[-1]["weight"] == 12.0
    assert (result.success_rate, result.value_error) == (0.9, 0.0)


def test_updates_after_the_best_last_evaluation_are_undone(monkeypatch):
    cfg = _cfg(
        frames=640,
        init_random_frames=128,
        updates_per_batch=2,
        eval_every=256,
        success_threshold=1.0,
        patience=5,
    )
    trainer, learner = _trainer(cfg)
    calls = _script(trainer, learner, [(0.5, 0.1, 0.0), (1.0, 0.0, 0.0)], monkeypatch)
    [(_, result)] = trainer.train()
    assert [c["frames"] for c in calls] == [256, 512]  # 128 frames of updates after the best
    assert (result.success_rate, result.value_error) == (1.0, 0.0)
    assert learner.weight.item() == calls[-1]["weight"]  # the weights that were evaluated
    assert result.restored_best


def test_evaluate_runs_the_greedy_policy_from_every_start():
    # the real evaluation on stage 1: the scripted policy reaches the target from every cell
    cfg = _cfg(frames=128, init_random_frames=0, gamma=0.9)
    task = _task()
    learner = FakeLearner(cfg, task.specs(1))
    with torch.no_grad():
        learner.weight.fill_(2.0)  # V(s) = 2 everywhere
    trainer = StageTrainer(1, learner, task.stage_env(1, NUM_ENVS), task.stage_eval_env(1), cfg)
    evaluation = trainer.evaluate(0)
    [success], [value_error], [ret] = (
        evaluation.success,
        evaluation.value_error,
        evaluation.discounted_return,
    )
    rows, cols = torch.meshgrid(torch.arange(SIZE), torch.arange(5, SIZE), indexing="ij")
    steps = (SIZE - 1 - rows) + (SIZE - 1 - cols)  # right, then down
    returns = 0.9 ** (steps[steps > 0] - 1.0)  # reward 1 on entering the target
    assert len(returns) == 49
    assert success == 1.0
    assert ret == pytest.approx(returns.mean().item())
    assert value_error == pytest.approx((2.0 - returns).mean().item())


# ------------------------------------------------------------------ backward schedule
def _tiny_dqn() -> DQNConfig:
    return DQNConfig(
        frames=256,
        frames_per_batch=128,
        num_envs=16,
        init_random_frames=128,
        batch_size=32,
        updates_per_batch=2,
        eval_every=0,
        tau=0.5,
    )


def test_train_backward_hands_a_frozen_target_value_to_the_previous_stage(monkeypatch):
    calls: list[tuple[str, int, object, object]] = []
    stage_env, stage_eval_env = StagedTask.stage_env, StagedTask.stage_eval_env

    def spy_env(self, stage, batch_size, next_value=None, **kw):
        env = stage_env(self, stage, batch_size, next_value, **kw)
        calls.append(("train", stage, next_value, env))
        return env

    def spy_eval_env(self, stage, next_value=None, **kw):
        env = stage_eval_env(self, stage, next_value, **kw)
        calls.append(("eval", stage, next_value, env))
        return env

    monkeypatch.setattr(StagedTask, "stage_env", spy_env)
    monkeypatch.setattr(StagedTask, "stage_eval_env", spy_eval_env)
    task = _task(_tiny_dqn())
    [run] = train_backward(task, [0])
    learners, results = run.learners, run.results
    assert [r.frames for r in results] == [256, 256]
    assert [(kind, stage) for kind, stage, _, _ in calls] == [
        ("train", 1),
        ("eval", 1),
        ("train", 0),
        ("eval", 0),
    ]
    assert all(nv is None for _, stage, nv, _ in calls if stage == 1)

    stage1 = learners[1]
    obs = task.base_env(64, start_stage=1).reset()["observation"]

    def out(module) -> torch.Tensor:
        with torch.no_grad():
            return module(TensorDict(observation=obs.clone(), batch_size=[64]))["state_value"]

    target = QMaxValue(with_params(stage1.qnet, stage1.loss.target_value_network_params))
    expected = out(target)
    assert torch.allclose(out(stage1.value()), expected)
    assert not torch.allclose(out(QMaxValue(stage1.qnet)), expected)  # the targets lag
    stage0 = [(kind, nv, env) for kind, stage, nv, env in calls if stage == 0]
    assert len(stage0) == 2
    # perturb stage 1's online and target networks: the handed-over value must not move
    with torch.no_grad():
        for p in stage1.qnet.parameters():
            p.add_(torch.randn_like(p))
        stage1.loss.target_value_network_params.apply_(lambda p: p.add_(1.0))
    online = out(QMaxValue(stage1.qnet))
    for _, next_value, env in stage0:
        assert next_value is not None
        assert torch.allclose(out(next_value), expected)
        assert not torch.allclose(out(next_value), online)
        transform = next(t for t in env.transform if isinstance(t, StageTransform))
        assert transform.train_stage == 0
        assert torch.allclose(out(transform.next_value), expected)


def test_train_stage_is_the_stage_of_a_backward_run():
    # a stage trained alone, given the next stage's value, is that stage of a whole run with the
    # same seed (what scripts/benchmark_stage.py relies on): the same weights and result
    task = _task(dataclasses.replace(_tiny_dqn(), eval_every=128))
    [run] = train_backward(task, [5])
    learners, results = run.learners, run.results
    [(last, last_result)] = train_stage(task, 1, seeds=[5])
    [(first, first_result)] = train_stage(task, 0, learners[1].value(), seeds=[5])
    for alone, result, k in ((first, first_result, 0), (last, last_result, 1)):
        assert result.success_rate is not None  # evaluated: its eval env's seed matters too
        assert (result.frames, result.updates, result.success_rate, result.value_error) == (
            results[k].frames,
            results[k].updates,
            results[k].success_rate,
            results[k].value_error,
        )
        whole = learners[k].state_dict()
        assert all(torch.equal(v, whole[key]) for key, v in alone.state_dict().items())
    [(other, _)] = train_stage(task, 1, seeds=[6])
    assert not all(torch.equal(v, last.state_dict()[key]) for key, v in other.state_dict().items())
    with pytest.raises(ValueError, match="pass next_value"):
        train_stage(task, 0, seeds=[5])


@pytest.mark.parametrize("gammas", ["homo", "hetero"])
def test_grid_world_stage_evaluation_depends_on_the_weights_only(hydra_compose, gammas):
    # what lets the grid world stop a stage at its first passing evaluation (patience: 1): the
    # env is deterministic and every start state is evaluated, so the evaluation is exact, not
    # a sample that a second evaluation of the same weights could contradict
    cfg = hydra_compose("task=gridworld", f"task/gammas={gammas}", "task.env.size=10")
    task = StagedTask(cfg.task)
    stage = 0
    scfg = task.stage_cfg(stage)
    assert scfg.patience == 1
    torch.manual_seed(0)
    learner = DQNLearner(scfg, task.specs(stage))
    next_value = DQNLearner(task.stage_cfg(stage + 1), task.specs(stage + 1)).value()
    results = []
    for seed in (0, 1):
        eval_env = task.stage_eval_env(stage, next_value)
        eval_env.set_seed(seed)
        env = task.stage_env(stage, 4, next_value)
        trainer = StageTrainer(stage, learner, env, eval_env, scfg)
        results.append(trainer.evaluate(frames=0))
    assert results[0] == results[1]
    assert eval_env.batch_size.numel() == len(task.start_states(stage)["start_cell"])
