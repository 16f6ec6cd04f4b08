"""Each algorithm's loss, the one its update runs, computes what torchrl's loss module does.

Each check builds a learner, moves its target networks away from the online ones (so that a
loss reading the wrong parameters shows), and compares the losses and the gradients of the
learner's loss with the torchrl loss module's own forward (the reference) on the same weights
and batch.
"""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from test_shared_encoder import IMAGE, SMALL
from test_shared_encoder import batch as image_batch
from torchrl.data import Bounded, Categorical

from torchrl_stages.learners import StageSpecs
from torchrl_stages.learners.ddpg import DDPGConfig, DDPGLearner
from torchrl_stages.learners.discrete_sac import DiscreteSACConfig, DiscreteSACLearner
from torchrl_stages.learners.dqn import DQNConfig, DQNLearner
from torchrl_stages.learners.sac import SACConfig, SACLearner
from torchrl_stages.learners.td3 import TD3Config, TD3Learner
from torchrl_stages.runs.experiment import compile_mode

DISCRETE = StageSpecs(["observation"], 2, "action", Categorical(4))
# non-trivial bounds: the actor's tanh is rescaled into them
CONTINUOUS = StageSpecs(
    ["observation"], 3, "action", Bounded(torch.tensor([-1.0, -2.0]), torch.tensor([1.0, 0.5]))
)


def batch(obs_dim: int, action: torch.Tensor, n: int = 64) -> TensorDict:
    g = torch.Generator().manual_seed(3)
    return TensorDict(
        observation=torch.rand(n, obs_dim, generator=g) * 5,
        action=action,
        steps_to_next_obs=torch.rand(n, 1, generator=g) * 3,  # per-transition discounts
        next=TensorDict(
            observation=torch.rand(n, obs_dim, generator=g) * 5,
            reward=torch.rand(n, 1, generator=g),
            terminated=torch.rand(n, 1, generator=g) < 0.2,
            done=torch.rand(n, 1, generator=g) < 0.3,
            batch_size=[n],
        ),
        batch_size=[n],
    )


def perturb(params) -> None:
    """Moves the learnable entries (not the tanh bounds' buffers) of ``params``."""
    with torch.no_grad():
        for key, p in params.items(True, True):
            if not any("low" in k or "high" in k for k in key):
                p.add_(0.3 * torch.randn_like(p))


def grads(params) -> list[torch.Tensor | None]:
    return [None if p.grad is None else p.grad.clone() for p in params.values(True, True)]


def reference_penalty(learner, data) -> torch.Tensor | float:
    """``saturation_penalty * mean(relu(|u| - 2)^2)`` over the trained actor's pre-tanh outputs
    ``u`` on the batch (what the actor-critic losses add), computed here on its own."""
    if learner.cfg.saturation_penalty <= 0:
        return 0.0
    u = learner.actor_module(*learner.inputs(data))
    return learner.cfg.saturation_penalty * (u.abs() - 2.0).clamp_min(0.0).pow(2).mean()


def assert_same_grads(a, b) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert (x is None) == (y is None)
        if x is not None:
            torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-6)


def assert_dqn_loss_is(learner: DQNLearner, data: TensorDict, reference_data: TensorDict) -> None:
    """The learner's loss on ``data`` is torchrl's ``DQNLoss`` on ``reference_data``, gradients
    included."""
    reference = learner.loss(reference_data.clone())["loss"]
    reference.backward()
    expected = grads(learner.loss.value_network_params)
    learner.optimizers["qvalue"].zero_grad()
    fast = learner._plain_loss(data.clone())
    fast.backward()
    torch.testing.assert_close(fast, reference)
    assert_same_grads(grads(learner.loss.value_network_params), expected)


@pytest.mark.parametrize("double", [True, False])
@pytest.mark.parametrize("dueling", [True, False])
@pytest.mark.parametrize("loss_function", ["l2", "smooth_l1"])
def test_dqn_loss_is_torchrls_dqn_loss(double, dueling, loss_function):
    cfg = DQNConfig(
        double_dqn=double, dueling=dueling, fourier_features=3, loss_function=loss_function
    )
    learner = DQNLearner(OmegaConf.structured(cfg), DISCRETE)
    perturb(learner.loss.target_value_network_params)
    data = batch(2, torch.randint(4, (64,)))
    assert_dqn_loss_is(learner, data, data)


@pytest.mark.parametrize("double", [True, False])
def test_advantage_learning_is_torchrls_dqn_loss_with_the_gap_off_the_reward(double):
    """Its target is DQN's less ``alpha (max_b Q_target(s, b) - Q_target(s, a))``: torchrl's
    loss on the batch whose rewards carry that term is the reference."""
    alpha = 0.9
    cfg = DQNConfig(double_dqn=double, advantage_learning=alpha, fourier_features=3)
    learner = DQNLearner(OmegaConf.structured(cfg), DISCRETE)
    perturb(learner.loss.target_value_network_params)
    data = batch(2, torch.randint(4, (64,)))
    with torch.no_grad(), learner.loss.target_value_network_params.to_module(learner.qnet):
        q_target = learner.qnet(data.clone())["action_value"]
    gap = q_target.max(-1, keepdim=True).values - q_target.gather(-1, data["action"][:, None])
    assert (gap >= 0).all() and (gap > 0).any()
    shifted = data.clone()
    shifted["next", "reward"] = data["next", "reward"] - alpha * gap
    assert_dqn_loss_is(learner, data, shifted)


@pytest.mark.parametrize("penalty", [0.0, 1.0])
def test_ddpg_losses_are_torchrls_ddpg_loss(penalty):
    learner = DDPGLearner(OmegaConf.structured(DDPGConfig(saturation_penalty=penalty)), CONTINUOUS)
    perturb(learner.loss.target_value_network_params)
    perturb(learner.loss.target_actor_network_params)
    with torch.no_grad():  # push the actor into saturation, where the penalty applies
        for p in learner.actor_module.parameters():
            p.mul_(3)
    data = batch(3, torch.rand(64, 2) * 2 - 1)
    out, expected_penalty = learner.loss(data.clone()), reference_penalty(learner, data)
    (out["loss_actor"] + out["loss_value"] + expected_penalty).backward()
    params = [learner.loss.actor_network_params, learner.loss.value_network_params]
    expected = [g for p in params for g in grads(p)]
    for optimizer in learner.optimizers.values():
        optimizer.zero_grad()
    loss_actor, loss_value, fast_penalty = learner._plain_losses(data.clone())
    (loss_actor + loss_value + fast_penalty).backward()
    torch.testing.assert_close(loss_actor, out["loss_actor"])
    torch.testing.assert_close(loss_value, out["loss_value"])
    torch.testing.assert_close(torch.as_tensor(fast_penalty), torch.as_tensor(expected_penalty))
    assert_same_grads([g for p in params for g in grads(p)], expected)


@pytest.mark.parametrize("penalty", [0.0, 1.0])
def test_td3_losses_are_torchrls_td3_loss(penalty):
    learner = TD3Learner(OmegaConf.structured(TD3Config(saturation_penalty=penalty)), CONTINUOUS)
    perturb(learner.loss.target_qvalue_network_params)
    perturb(learner.loss.target_actor_network_params)
    data = batch(3, torch.rand(64, 2) * 2 - 1)
    critics = learner.loss.qvalue_network_params
    torch.manual_seed(5)  # the target policy smoothing noise: the same draws
    reference, _ = learner.loss.value_loss(data.clone())
    reference.backward()
    expected = grads(critics)
    learner.optimizers["critic"].zero_grad()
    torch.manual_seed(5)
    fast = learner._plain_value_loss(data.clone())
    fast.backward()
    torch.testing.assert_close(fast, reference)
    assert_same_grads(grads(critics), expected)
    for optimizer in learner.optimizers.values():
        optimizer.zero_grad()
    (loss_actor, _), expected_penalty = (
        learner.loss.actor_loss(data.clone()),
        reference_penalty(learner, data),
    )
    (loss_actor + expected_penalty).backward()
    expected = grads(learner.loss.actor_network_params) + grads(critics)
    for optimizer in learner.optimizers.values():
        optimizer.zero_grad()
    fast_actor, fast_penalty = learner._plain_actor_loss(data.clone())
    (fast_actor + fast_penalty).backward()
    torch.testing.assert_close(fast_actor, loss_actor)
    assert_same_grads(grads(learner.loss.actor_network_params) + grads(critics), expected)


def _compare_sac(learner, data) -> None:
    """The learner's three losses and their gradients against the torchrl loss's forward,
    both drawing from the same seed (the next actions first, then the actor's)."""
    loss = learner.loss
    params = [loss.actor_network_params, loss.qvalue_network_params]
    perturb(loss.target_qvalue_network_params)
    with torch.no_grad():
        loss.log_alpha.fill_(-0.7)  # alpha away from 1
    torch.manual_seed(5)
    out = loss(data.clone())
    (out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]).backward()
    expected = [g for p in params for g in grads(p)] + [loss.log_alpha.grad.clone()]
    for optimizer in learner.optimizers.values():
        optimizer.zero_grad()
    torch.manual_seed(5)
    loss_actor, loss_q, loss_alpha = learner._plain_losses(data.clone())
    (loss_actor + loss_q + loss_alpha).backward()
    torch.testing.assert_close(loss_actor, out["loss_actor"])
    torch.testing.assert_close(loss_q, out["loss_qvalue"])
    torch.testing.assert_close(loss_alpha, out["loss_alpha"])
    assert_same_grads([g for p in params for g in grads(p)] + [loss.log_alpha.grad], expected)


@pytest.mark.parametrize("loss_function", ["l2", "smooth_l1"])
def test_sac_losses_are_torchrls_sac_loss(loss_function):
    cfg = SACConfig(loss_function=loss_function)
    learner = SACLearner(OmegaConf.structured(cfg), CONTINUOUS)
    _compare_sac(learner, batch(3, torch.rand(64, 2) * 2 - 1))


@pytest.mark.parametrize("loss_function", ["l2", "smooth_l1"])
def test_discrete_sac_losses_are_torchrls_discrete_sac_loss(loss_function):
    cfg = DiscreteSACConfig(loss_function=loss_function, fourier_features=2)
    learner = DiscreteSACLearner(OmegaConf.structured(cfg), DISCRETE)
    _compare_sac(learner, batch(2, torch.randint(4, (64,))))


def test_discrete_sac_value_is_the_soft_value_of_its_critic_targets():
    """``V(s')`` is what the torchrl loss bootstraps from: with reward 0 and no termination,
    its target is ``gamma V(s')``."""
    learner = DiscreteSACLearner(OmegaConf.structured(DiscreteSACConfig(gamma=0.9)), DISCRETE)
    perturb(learner.loss.target_qvalue_network_params)
    data = batch(2, torch.randint(4, (64,)))
    data["next", "reward"].zero_()
    data["next", "terminated"].zero_()
    del data["steps_to_next_obs"]
    target = learner.loss._compute_target(data.clone())
    value = learner.value()(data["next"].select("observation").clone())["state_value"]
    torch.testing.assert_close(0.9 * value.squeeze(-1), target)


def test_sac_value_is_a_fixed_function_of_the_state_and_the_soft_value():
    learner = SACLearner(OmegaConf.structured(SACConfig(value_samples=4096)), CONTINUOUS)
    obs = TensorDict(observation=torch.rand(5, 3), batch_size=[5])
    value = learner.value()
    state = torch.get_rng_state()
    first = value(obs.clone())["state_value"]
    assert torch.equal(torch.get_rng_state(), state)  # the global generator is left alone
    assert torch.equal(value(obs.clone())["state_value"], first)  # a function of s
    # the expectation it estimates, from independent draws of the same policy
    loss = learner.loss
    with torch.no_grad():
        dist = learner._dist(learner.actor_module(obs["observation"]))
        action, log_prob = dist.rsample((4096,)), None
        log_prob = dist.log_prob(action)
        obs_k = obs["observation"].expand(4096, 5, 3)
        critics = loss.target_qvalue_network_params
        q = torch.stack(learner.critic_values(critics, [obs_k], action)).amin(0)
        expected = (q - loss.log_alpha.exp() * log_prob.unsqueeze(-1)).mean(0)
    torch.testing.assert_close(first, expected, rtol=0.05, atol=0.05)


def test_fused_soft_update_moves_targets_by_tau():
    learner = DQNLearner(OmegaConf.structured(DQNConfig(tau=0.3)), DISCRETE)
    perturb(learner.loss.value_network_params)
    online = [p.detach().clone() for p in learner.loss.value_network_params.values(True, True)]
    target = [
        p.detach().clone() for p in learner.loss.target_value_network_params.values(True, True)
    ]
    learner.target_updater.step()
    after = learner.loss.target_value_network_params.values(True, True)
    for new, old, source in zip(after, target, online, strict=True):
        torch.testing.assert_close(new, old + 0.3 * (source - old))


def compiled_learner(name: str, compile: str):
    """A learner of each algorithm: DQN (dueling, Fourier features), DDPG, and TD3 with the
    cargo slider's shared CNN encoder; its replay batches; and how many losses it compiles."""
    if name == "dqn":
        cfg = DQNConfig(dueling=True, fourier_features=2)
        learner = DQNLearner(OmegaConf.structured(cfg), DISCRETE, compile=compile)
        return learner, lambda seed: batch(2, torch.randint(4, (64,))), 1
    if name == "ddpg":
        learner = DDPGLearner(OmegaConf.structured(DDPGConfig()), CONTINUOUS, compile=compile)
        return learner, lambda seed: batch(3, torch.rand(64, 2) * 2 - 1), 1
    if name == "sac":  # with the shared CNN encoder
        cfg = SACConfig(**SMALL, shared_encoder=True)
        learner = SACLearner(OmegaConf.structured(cfg), IMAGE, compile=compile)
        return learner, lambda seed: image_batch(seed=seed), 1
    if name == "discrete_sac":
        cfg = DiscreteSACConfig(fourier_features=2)
        learner = DiscreteSACLearner(OmegaConf.structured(cfg), DISCRETE, compile=compile)
        return learner, lambda seed: batch(2, torch.randint(4, (64,))), 1
    cfg = TD3Config(**SMALL, shared_encoder=True, policy_update_delay=1)
    learner = TD3Learner(OmegaConf.structured(cfg), IMAGE, compile=compile)
    return learner, lambda seed: image_batch(seed=seed), 2


@pytest.mark.parametrize("name", ["dqn", "ddpg", "td3"])
def test_compiled_losses_are_one_graph_and_the_same_updates(name, monkeypatch):
    """``compile`` != off runs each loss through ``torch.compile``. Dynamo's eager
    backend stands in for inductor here (its code generation takes about 15 s per learner on a
    CPU): the capture is the same, each loss must be one graph without a break (a break splits
    the CUDA graphs of ``reduce-overhead``), and the updates must equal ``compile=off``'s bit
    for bit."""
    compile = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, mode=None: compile(fn, backend="eager"))
    torch._dynamo.reset()
    counters = torch._dynamo.utils.counters
    counters.clear()
    states = {}
    for mode in ("default", "off"):
        torch.manual_seed(0)
        learner, data, losses = compiled_learner(name, mode)
        for seed in range(3):
            torch.manual_seed(10 + seed)  # the same batches and TD3 smoothing noise
            learner.update(data(seed))
        states[mode] = learner.state_dict()
    assert counters["stats"]["unique_graphs"] == losses
    assert not counters["graph_break"]
    assert states["default"].keys() == states["off"].keys()
    for key, value in states["default"].items():
        assert torch.equal(value, states["off"][key]), key


@pytest.mark.parametrize("name", ["dqn", "ddpg", "td3", "sac", "discrete_sac"])
def test_update_returns_losses_the_next_replay_cannot_overwrite(name):
    """Under ``compile=reduce-overhead`` each loss is a CUDA graph's static output,
    rewritten by the graph's next replay while the stage still holds the batch's losses for
    its log. Writing over every output of the losses after the update stands in for that
    replay: the losses the update returned must not change."""
    torch.manual_seed(0)
    learner, data, _ = compiled_learner(name, "off")
    outputs = []
    for attr in ("_loss_fn", "_losses", "_value_loss", "_actor_loss"):
        if hasattr(learner, attr):
            fn = getattr(learner, attr)

            def recorded(batch, fn=fn):
                out = fn(batch)
                outputs.extend(out if isinstance(out, tuple) else [out])
                return out

            setattr(learner, attr, recorded)
    losses = learner.update(data(0))
    before = {k: v.clone() for k, v in losses.items()}
    assert outputs
    with torch.no_grad():
        for out in outputs:
            if isinstance(out, torch.Tensor):
                out.fill_(float("nan"))
    for key, value in losses.items():
        assert torch.equal(value, before[key]), key


@pytest.mark.parametrize(
    ("compile", "device", "expected"),
    [
        ("auto", "cpu", "off"),
        ("auto", "cuda", "reduce-overhead"),
        ("auto", "cuda:1", "reduce-overhead"),
        ("default", "cpu", "default"),
        ("off", "cuda", "off"),
    ],
)
def test_compile_auto_is_off_on_cpu_and_cuda_graphs_on_a_gpu(compile, device, expected):
    assert compile_mode(OmegaConf.create({"compile": compile, "device": device})) == expected
