"""SeedReplayBuffer: one seed's ring samples what torchrl's replay buffer samples, with wraps,
partial fills and image entries, and a checkpoint restores it."""

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_stages.replay import SeedReplayBuffer


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


def test_one_seed_samples_what_torchrl_samples():
    for size, added in ((64, [40]), (16, [12, 12])):  # partly filled; wrapped around
        reference = TensorDictReplayBuffer(storage=LazyTensorStorage(size))
        ours = SeedReplayBuffer(size, num_seeds=1)
        for n in added:
            data = transitions(n)
            reference.extend(data)
            ours.extend(data)
        for seed in range(3):
            torch.manual_seed(seed)
            expected = reference.sample(32)
            torch.manual_seed(seed)
            got = ours.sample(32)[0]
            assert got.batch_size == expected.batch_size == torch.Size([32])
            for key in got.keys(True, True):
                assert got[key].dtype == expected[key].dtype
                assert torch.equal(got[key], expected[key]), key


def test_a_checkpoint_restores_the_rings():
    ours = SeedReplayBuffer(16, num_seeds=2)
    ours.extend(transitions(20))  # each seed's ring: 10 transitions
    ours.extend(transitions(5), seeds=torch.tensor([1, 1, 1, 1, 1]))
    restored = SeedReplayBuffer(16, num_seeds=2)
    restored.load_state_dict(ours.state_dict())
    assert restored.counts.tolist() == ours.counts.tolist() == [10, 15]
    assert (restored.held() == ours.held()).all()
    torch.manual_seed(0)
    expected = ours.sample(8)
    torch.manual_seed(0)
    assert (restored.sample(8) == expected).all()
