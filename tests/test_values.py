"""State-value adapters: V = max_a Q, Q(s, mu(s)), min of twin critics, and the
learners' ``value()`` built from their TARGET networks."""

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded, Categorical
from torchrl.modules import MLP, QValueActor, ValueOperator

from torchrl_stages.learners import StageSpecs
from torchrl_stages.learners.ddpg import DDPGConfig, DDPGLearner
from torchrl_stages.learners.dqn import DQNConfig, DQNLearner
from torchrl_stages.learners.td3 import TD3Config, TD3Learner
from torchrl_stages.transforms import freeze
from torchrl_stages.values import ActorCriticValue, QMaxValue, with_params

OBS = torch.tensor([[1.0, 2.0], [-1.0, 3.0], [0.5, -2.0], [0.0, 0.0]])


def linear(in_features, out_features, weight, bias):
    lin = nn.Linear(in_features, out_features)
    with torch.no_grad():
        lin.weight.copy_(torch.as_tensor(weight, dtype=torch.float32))
        lin.bias.copy_(torch.as_tensor(bias, dtype=torch.float32))
    return lin


def obs_td(obs=OBS, **extra):
    return TensorDict(observation=obs.clone(), **extra, batch_size=[obs.shape[0]])


def assert_only_state_value_written(v, td):
    before = td.clone()
    out = v(td)
    assert out is td
    assert set(td.keys(True, True)) == set(before.keys(True, True)) | {"state_value"}
    for key in before.keys(True, True):
        assert torch.equal(td[key], before[key])
    return td["state_value"]


# ---------------------------------------------------------------------- adapters, known nets
def test_qmax_value_of_a_qvalue_actor():
    w = [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]
    b = [0.0, 0.0, -1.0]
    qactor = QValueActor(linear(2, 3, w, b), in_keys=["observation"], spec=Categorical(3))
    v = QMaxValue(qactor)
    assert v.in_keys == ["observation"] and v.out_keys == ["state_value"]
    td = obs_td(other=torch.arange(4))
    value = assert_only_state_value_written(v, td)
    # Q rows: [1, 2, 2], [-1, 3, 1], [0.5, -2, -2.5], [0, 0, -1]
    assert value.shape == (4, 1)
    assert value.squeeze(-1).tolist() == pytest.approx([2.0, 3.0, 0.5, 0.0])
    # "action", "action_value", "chosen_action_value" of the Q actor stay out of the input
    assert "action" not in td.keys()


def test_qmax_value_batched_time_dims():
    qactor = QValueActor(
        linear(2, 2, [[1.0, 0.0], [0.0, 1.0]], [0.0, 0.0]),
        in_keys=["observation"],
        spec=Categorical(2),
    )
    obs = torch.arange(12.0).reshape(2, 3, 2)
    td = TensorDict(observation=obs, batch_size=[2, 3])
    value = QMaxValue(qactor)(td)["state_value"]
    assert value.shape == (2, 3, 1)
    assert torch.equal(value, obs.max(-1, keepdim=True).values)


class _TwoInputs(nn.Module):
    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(5, 8), nn.ReLU(), nn.Linear(8, 4))

    def forward(self, image, vector):
        return self.net(torch.cat([image.flatten(-2).float().mean(-1), vector], -1))


def test_qmax_value_calls_a_qvalue_actors_network_directly_with_the_same_values():
    torch.manual_seed(0)
    qactor = QValueActor(_TwoInputs(), in_keys=["image", "vector"], spec=Categorical(4))
    td = TensorDict(
        image=torch.randint(0, 2, (6, 3, 2, 2), dtype=torch.uint8),
        vector=torch.randn(6, 2),
        batch_size=[6],
    )
    v = QMaxValue(qactor)
    assert v._network() is qactor.module[0]
    calls = []
    handle = qactor.register_forward_hook(lambda *args: calls.append(1))
    fast = v(td.clone())["state_value"]
    handle.remove()
    assert not calls  # the TensorDict modules around the network did not run
    expected = qactor(td.clone())["action_value"].max(-1, keepdim=True).values
    assert torch.equal(fast, expected)  # bit for bit
    # a frozen copy keeps the direct call, on its own (copied) network
    frozen = freeze(v)
    assert frozen._network() is frozen.qvalue_net.module[0]
    assert torch.equal(frozen(td.clone())["state_value"], expected)


def test_qmax_value_runs_other_modules_whole():
    q = TensorDictModule(lambda obs: obs * 2, ["observation"], ["action_value"])
    assert QMaxValue(q)._network() is None
    # a QValueActor whose action values are another key: the whole actor runs
    qactor = QValueActor(
        linear(2, 2, [[1.0, 0.0], [0.0, 1.0]], [0.0, 0.0]),
        in_keys=["observation"],
        spec=Categorical(2),
    )
    assert QMaxValue(qactor, action_value_key="chosen_action_value")._network() is None


def make_actor_critic():
    """mu(s) = 0.5 * s0 - s1; Q1(s, a) = s0 + 2 a + 1; Q2(s, a) = -s1 + a."""
    actor = TensorDictModule(linear(2, 1, [[0.5, -1.0]], [0.0]), ["observation"], ["action"])

    def critic(weight, bias):
        mlp = MLP(in_features=3, out_features=1, num_cells=[])
        with torch.no_grad():
            lin = [m for m in mlp.modules() if isinstance(m, nn.Linear)]
            assert len(lin) == 1
            lin[0].weight.copy_(torch.tensor([weight]))
            lin[0].bias.fill_(bias)
        return ValueOperator(mlp, in_keys=["observation", "action"])

    return actor, critic([1.0, 0.0, 2.0], 1.0), critic([0.0, -1.0, 1.0], 0.0)


def test_actor_critic_value_one_critic():
    actor, q1, _ = make_actor_critic()
    v = ActorCriticValue(actor, [q1])
    assert v.in_keys == ["observation"]
    value = assert_only_state_value_written(v, obs_td())
    s0, s1 = OBS[:, 0], OBS[:, 1]
    mu = 0.5 * s0 - s1
    assert value.squeeze(-1).tolist() == pytest.approx((s0 + 2 * mu + 1).tolist())


def test_actor_critic_value_two_critics_is_the_min():
    actor, q1, q2 = make_actor_critic()
    v = ActorCriticValue(actor, [q1, q2])
    value = assert_only_state_value_written(v, obs_td())
    s0, s1 = OBS[:, 0], OBS[:, 1]
    mu = 0.5 * s0 - s1
    v1, v2 = s0 + 2 * mu + 1, -s1 + mu
    expected = torch.minimum(v1, v2)
    # each critic is the min somewhere, so this is not just one of them
    assert (v1 < v2).any() and (v2 < v1).any()
    assert value.squeeze(-1).tolist() == pytest.approx(expected.tolist())


def test_actor_critic_value_needs_a_critic():
    actor, _, _ = make_actor_critic()
    with pytest.raises(ValueError):
        ActorCriticValue(actor, [])


def test_with_params_is_a_copy_holding_the_params():
    net = nn.Sequential(nn.Linear(2, 3), nn.ReLU(), nn.Linear(3, 1))
    params = TensorDict.from_module(net).data.clone().apply(torch.ones_like)
    copy = with_params(net, params)
    assert copy is not net
    assert all(torch.equal(p, torch.ones_like(p)) for p in copy.parameters())
    assert not any(torch.equal(p, torch.ones_like(p)) for p in net.parameters())
    # the copy does not share storage with ``params``
    params.apply_(lambda t: t.zero_())
    assert all(torch.equal(p, torch.ones_like(p)) for p in copy.parameters())


# ---------------------------------------------------------------------- learners' value()
def mlp_forward(params: dict, prefix: str, x: torch.Tensor, layers=(0, 2, 4)) -> torch.Tensor:
    """The learners' MLPs (Linear-Tanh-Linear-Tanh-Linear, torchrl's default activation)
    computed by hand from ``params``."""
    for i, layer in enumerate(layers):
        x = x @ params[f"{prefix}{layer}.weight"].T + params[f"{prefix}{layer}.bias"]
        if i < len(layers) - 1:
            x = torch.tanh(x)
    return x


def flat(params) -> dict:
    return dict(params.detach().flatten_keys(".").items())


def dqn_batch(n=64, num_actions=4):
    g = torch.Generator().manual_seed(1)
    return TensorDict(
        observation=torch.rand(n, 2, generator=g),
        action=torch.randint(num_actions, (n,), generator=g),
        next=TensorDict(
            observation=torch.rand(n, 2, generator=g),
            reward=torch.rand(n, 1, generator=g),
            done=torch.zeros(n, 1, dtype=torch.bool),
            terminated=torch.zeros(n, 1, dtype=torch.bool),
            batch_size=[n],
        ),
        batch_size=[n],
    )


def ac_batch(n=64, action_dim=1):
    td = dqn_batch(n)
    g = torch.Generator().manual_seed(2)
    td["action"] = torch.rand(n, action_dim, generator=g) * 2 - 1
    return td


def test_dqn_value_uses_target_params():
    cfg = OmegaConf.structured(DQNConfig(num_cells=[16, 16], tau=0.1, lr=1e-2, dueling=False))
    learner = DQNLearner(cfg, StageSpecs(["observation"], 2, "action", Categorical(4)))
    batch = dqn_batch()
    for _ in range(5):
        learner.update(batch.clone())
    td = obs_td()
    value = assert_only_state_value_written(learner.value(), td)
    target = flat(learner.loss.target_value_network_params)
    expected = mlp_forward(target, "module.0.module.", OBS).max(-1, keepdim=True).values
    assert torch.allclose(value, expected, atol=1e-6)
    online = learner.qnet(obs_td())["action_value"].max(-1, keepdim=True).values
    assert not torch.allclose(value, online, atol=1e-4)
    # the online weights change; the value module (a snapshot of the targets) does not
    v = learner.value()
    with torch.no_grad():
        for p in learner.qnet.parameters():
            p.add_(1.0)
    assert torch.allclose(v(obs_td())["state_value"], expected, atol=1e-6)
    assert torch.allclose(learner.value()(obs_td())["state_value"], expected, atol=1e-6)


def test_dqn_value_before_any_update_equals_online():
    cfg = OmegaConf.structured(DQNConfig(num_cells=[8]))
    learner = DQNLearner(cfg, StageSpecs(["observation"], 2, "action", Categorical(3)))
    value = learner.value()(obs_td())["state_value"]
    online = learner.qnet(obs_td())["action_value"].max(-1, keepdim=True).values
    assert torch.allclose(value, online.detach())
    # value() is a copy (the caller freezes it): it shares no storage with the learner
    ptrs = {p.data_ptr() for p in learner.parameters()}
    assert not ptrs & {p.data_ptr() for p in learner.value().parameters()}
    frozen = freeze(learner.value())
    assert not frozen(obs_td())["state_value"].requires_grad


def test_ddpg_value_uses_target_actor_and_critic():
    cfg = OmegaConf.structured(DDPGConfig(num_cells=[16, 16], tau=0.1, lr=1e-2, actor_lr=1e-2))
    learner = DDPGLearner(
        cfg, StageSpecs(["observation"], 2, "action", Bounded(-1.0, 1.0, shape=(1,)))
    )
    batch = ac_batch()
    for _ in range(5):
        learner.update(batch.clone())
    loss = learner.loss
    actor_p = flat(loss.target_actor_network_params)
    critic_p = flat(loss.target_value_network_params)
    mu = torch.tanh(mlp_forward(actor_p, "module.0.module.", OBS))  # bounds [-1, 1]
    expected = mlp_forward(critic_p, "module.", torch.cat([OBS, mu], -1))
    value = assert_only_state_value_written(learner.value(), obs_td())
    assert torch.allclose(value, expected, atol=1e-5)
    # not the online networks
    online_mu = learner.actor(obs_td())["action"]
    online = learner.critic(obs_td(action=online_mu))["state_action_value"]
    assert not torch.allclose(value, online.detach(), atol=1e-4)


def test_td3_value_is_min_of_target_critics_at_target_action():
    cfg = OmegaConf.structured(
        TD3Config(num_cells=[16, 16], tau=0.1, lr=1e-2, actor_lr=1e-2, policy_update_delay=1)
    )
    learner = TD3Learner(
        cfg, StageSpecs(["observation"], 2, "action", Bounded(-2.0, 2.0, shape=(1,)))
    )
    batch = ac_batch()
    for _ in range(5):
        learner.update(batch.clone())
    loss = learner.loss
    # by hand from the loss' stacked target params
    actor_p = flat(loss.target_actor_network_params)
    mu = 2.0 * torch.tanh(mlp_forward(actor_p, "module.0.module.", OBS))  # bounds [-2, 2]
    qs = [
        mlp_forward(flat(loss.target_qvalue_network_params[i]), "module.", torch.cat([OBS, mu], -1))
        for i in range(2)
    ]
    assert not torch.allclose(qs[0], qs[1])
    expected = torch.minimum(*qs)
    value = assert_only_state_value_written(learner.value(), obs_td())
    assert torch.allclose(value, expected, atol=1e-5)
    # the same through with_params, as the brief describes it
    actor_t = with_params(learner.actor, loss.target_actor_network_params)
    td_a = actor_t(obs_td())
    assert torch.allclose(td_a["action"], mu, atol=1e-5)
    critics = [with_params(learner.critic, loss.target_qvalue_network_params[i]) for i in range(2)]
    manual = torch.stack([c(td_a.clone())["state_action_value"] for c in critics]).amin(0)
    assert torch.allclose(value, manual.detach(), atol=1e-6)
    # the loss' online critics give another value
    online = [
        mlp_forward(flat(loss.qvalue_network_params[i]), "module.", torch.cat([OBS, mu], -1))
        for i in range(2)
    ]
    assert not torch.allclose(value, torch.minimum(*online), atol=1e-4)
