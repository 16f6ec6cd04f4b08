"""GatherStorage: the same samples, checkpoints and stage runs as torchrl's LazyTensorStorage."""

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_stages import replay as replay_module
from torchrl_stages import stage as stage_module
from torchrl_stages.learners.dqn import DQNConfig, DQNLearner
from torchrl_stages.replay import GatherStorage
from torchrl_stages.task import StagedTask


def transitions(n: int) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    obs = {
        "window": torch.randint(0, 2, (n, 1, 10, 10), generator=g, dtype=torch.uint8),
        "target": torch.randn(n, 2, generator=g),
    }
    nxt = {k: v.roll(1, 0) for k, v in obs.items()}
    nxt["reward"] = torch.randn(n, 1, generator=g)
    nxt["done"] = torch.rand(n, 1, generator=g) < 0.1
    data = {**obs, "action": torch.randn(n, 1, generator=g), "next": nxt}
    return TensorDict(data, batch_size=[n])


def buffers(size: int) -> tuple[TensorDictReplayBuffer, TensorDictReplayBuffer]:
    plain = TensorDictReplayBuffer(storage=LazyTensorStorage(size))
    return plain, TensorDictReplayBuffer(storage=GatherStorage(size))


def test_samples_equal_lazy_tensor_storage():
    plain, gather = buffers(64)
    for rb in (plain, gather):
        rb.extend(transitions(40))  # partly filled: samples come from the first 40 only
    for seed in range(3):
        torch.manual_seed(seed)
        expected = plain.sample(32)
        torch.manual_seed(seed)
        got = gather.sample(32)
        assert got.batch_size == expected.batch_size == torch.Size([32])
        assert got["next"].batch_size == torch.Size([32])
        assert set(got.keys(True, True)) == set(expected.keys(True, True))
        for key in expected.keys(True, True):
            assert got[key].dtype == expected[key].dtype
            assert torch.equal(got[key], expected[key]), key
        assert int(got["index"].max()) < 40


def test_other_indices_and_checkpoints_as_parent():
    plain, gather = buffers(16)
    data = transitions(20)  # wraps around
    plain.extend(data)
    gather.extend(data)
    for index in (3, slice(2, 5), torch.arange(16) % 2 == 0):
        assert (gather.storage.get(index) == plain.storage.get(index)).all()
    restored = TensorDictReplayBuffer(storage=GatherStorage(16))
    restored.load_state_dict(plain.state_dict())  # a checkpoint of the parent's storage
    assert (restored.storage.get(torch.arange(16)) == plain.storage.get(torch.arange(16))).all()
    assert len(restored) == len(plain) == 16


def test_stage_runs_equal_with_lazy_tensor_storage(monkeypatch):
    """A DQN stage trained on GatherStorage ends with the weights it has on torchrl's storage."""
    stage_cfg = DQNConfig(gamma=0.9)
    task = StagedTask(
        OmegaConf.create(
            {
                "name": "grid",
                "stages": {"a": stage_cfg, "b": stage_cfg},
                "env": {
                    "_target_": "torchrl_stages.envs.GridWorldEnv",
                    "size": 10,
                    "num_stages": 2,
                },
            }
        )
    )
    cfg = OmegaConf.structured(
        DQNConfig(
            gamma=0.9,
            frames=1024,
            frames_per_batch=128,
            num_envs=16,
            batch_size=32,
            init_random_frames=128,
            updates_per_batch=4,
            eval_every=256,
        )
    )

    def train() -> dict[str, torch.Tensor]:
        torch.manual_seed(0)
        learner = DQNLearner(cfg, task.specs(1))
        env = task.stage_env(1, cfg.num_envs)
        env.set_seed(0)
        stage_module.StageTrainer(1, learner, env, task.stage_eval_env(1), cfg).train()
        return learner.state_dict()

    gathered = train()
    # the stage loop's buffers are built by replay.stage_replay_buffer
    monkeypatch.setattr(replay_module, "GatherStorage", LazyTensorStorage)
    plain = train()
    assert gathered.keys() == plain.keys()
    for key in plain:
        assert torch.equal(gathered[key], plain[key]), key
