"""Early stop and best-weights restoration of the stage loop."""

import pytest
import torch
from omegaconf import OmegaConf
from torch import nn

from torchrl_stages.early_stop import EarlyStop, can_stop_early
from torchrl_stages.learners.dqn import DQNConfig


def _cfg(**kw):
    return OmegaConf.structured(DQNConfig(**kw))


def _learner(value: float) -> nn.Module:
    module = nn.Linear(1, 1)
    module.weight.data.fill_(value)
    return module


def test_a_loop_can_stop_early_with_a_threshold_and_evaluations():
    assert can_stop_early(_cfg(success_threshold=0.9, eval_every=1000))
    assert not can_stop_early(_cfg(success_threshold=None, eval_every=1000))


def test_early_stop_needs_patience_tolerance_and_min_frames():
    monitor = EarlyStop(
        _cfg(success_threshold=1.0, value_tolerance=0.05, patience=2, min_frames=300)
    )
    learner = _learner(0.0)
    assert not monitor.record(learner, 1.0, 0.01, 100)
    assert not monitor.record(learner, 1.0, 0.20, 200)  # values not calibrated: streak resets
    assert not monitor.record(learner, 1.0, 0.01, 300)
    assert monitor.record(learner, 1.0, 0.01, 400)
    assert monitor.stopped and not monitor.restore_best(learner)
    assert monitor.final == (1.0, 0.01, None)


def test_without_value_tolerance_success_alone_stops_the_stage():
    monitor = EarlyStop(_cfg(success_threshold=0.98, value_tolerance=None, patience=2))
    learner = _learner(0.0)
    assert not monitor.record(learner, 0.97, 0.0, 100)
    assert not monitor.record(learner, 1.0, 0.9, 200)  # values far off: not checked
    assert monitor.record(learner, 0.98, 0.5, 300)
    assert monitor.stopped and monitor.final == (0.98, 0.5, None)


def test_budget_exhausted_restores_best_evaluation():
    monitor = EarlyStop(_cfg(success_threshold=1.0, patience=3))
    learner = _learner(0.0)
    for value, success, error in [(1.0, 0.5, 0.3), (2.0, 1.0, 0.02), (3.0, 0.8, 0.1)]:
        learner.weight.data.fill_(value)
        assert not monitor.record(learner, success, error, 0)
    assert monitor.restore_best(learner)
    assert learner.weight.item() == 2.0
    assert monitor.final == (1.0, 0.02, None)


def test_ties_prefer_lower_value_error_and_last_best_is_kept():
    monitor = EarlyStop(_cfg(success_threshold=None))
    learner = _learner(0.0)
    for value, error in [(1.0, 0.1), (2.0, 0.05)]:
        learner.weight.data.fill_(value)
        monitor.record(learner, 1.0, error, 0)
    assert not monitor.restore_best(learner)  # the last evaluation is the best one
    assert learner.weight.item() == 2.0


def test_keep_best_off_keeps_last_weights():
    monitor = EarlyStop(_cfg(keep_best=False))
    learner = _learner(5.0)
    monitor.record(learner, 1.0, 0.0, 0)
    learner.weight.data.fill_(6.0)
    monitor.record(learner, 0.0, 1.0, 0)
    assert not monitor.restore_best(learner)
    assert torch.equal(learner.weight, torch.full((1, 1), 6.0))
    assert monitor.final == (0.0, 1.0, None)


def test_keep_best_by_return_prefers_the_highest_discounted_return():
    monitor = EarlyStop(_cfg(success_threshold=None, keep_best_by="return"))
    learner = _learner(0.0)
    evals = [
        (1.0, 0.9, 0.01, 0.5),
        (2.0, 1.0, 0.3, 0.2),
        (3.0, 1.0, 0.2, 0.4),
        (4.0, 1.0, 0.1, 0.3),
    ]
    for value, success, error, ret in evals:
        learner.weight.data.fill_(value)
        monitor.record(learner, success, error, 0, ret)
    assert monitor.restore_best(learner)  # success first, then return (not value error)
    assert learner.weight.item() == 3.0
    assert monitor.final == (1.0, 0.2, 0.4)  # the return of the evaluation it restored


def test_final_return_is_that_of_the_evaluation_the_stage_ends_with():
    stopping = EarlyStop(_cfg(success_threshold=1.0, value_tolerance=None, patience=1))
    assert not stopping.record(_learner(0.0), 0.5, 0.1, 0, 0.7)
    assert stopping.record(_learner(0.0), 1.0, 0.1, 0, 0.3)
    assert stopping.final[2] == 0.3  # its stop, not its best return
    budget = EarlyStop(_cfg(success_threshold=1.0, patience=3))
    budget.record(_learner(0.0), 1.0, 0.02, 0, 0.6)
    budget.record(_learner(0.0), 0.8, 0.01, 0, 0.9)
    assert budget.final == (1.0, 0.02, 0.6)  # its best evaluation
    restored = EarlyStop(_cfg(success_threshold=1.0, patience=3))
    restored.load_state_dict(budget.state_dict())
    assert restored.final[2] == 0.6
    old = {k: v for k, v in budget.state_dict().items() if not k.endswith("_return")}
    restored.load_state_dict(old)  # a checkpoint from before the returns were kept
    assert restored.final == (1.0, 0.02, None)


def test_a_checkpoint_of_an_earlier_version_is_refused_with_the_fix(tmp_path):
    # the loops' counters of an earlier version (no format): its replay, early stop and
    # counters held another state, which this version would misread
    from torchrl_stages.checkpoint import CheckpointDamagedError, StageCheckpoints
    from torchrl_stages.loop import LoopCounters
    from torchrl_stages.schedules.joint import JointCounters

    checkpoints = StageCheckpoints(tmp_path / "stage_1", every=1)
    checkpoints.save(64, {"counters": {"next_eval": 128, "seconds": 1.0, "log": {}}})
    for counters in (LoopCounters(next_eval=0), JointCounters(2, 1)):
        with pytest.raises(CheckpointDamagedError, match="earlier version.*Fix: delete"):
            checkpoints.load(checkpoints.latest(), {"counters": counters})
    checkpoints.save(128, {"counters": LoopCounters(next_eval=256)})  # this version's
    restored = LoopCounters(next_eval=0)
    checkpoints.load(checkpoints.latest(), {"counters": restored})
    assert restored.next_eval == 256
