"""DDPG, TD3 and SAC with one input encoder for the actor and the critics (``shared_encoder``).

The shared path must compute TD3's losses for critics that read the actor's encoder (the target
critics the target actor's), train the encoder with the critic loss alone, hand on the value of
the same networks, and save and restore exactly.
"""

from __future__ import annotations

import io

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torch.func import functional_call
from torchrl.data import Bounded

from torchrl_stages.learners import StageSpecs
from torchrl_stages.learners.ddpg import DDPGConfig, DDPGLearner
from torchrl_stages.learners.sac import SACConfig, SACLearner
from torchrl_stages.learners.td3 import TD3Config, TD3Learner

# a 1 x 6 x 6 image and a 2-vector, like the cargo stages' window and target
IMAGE = StageSpecs(
    ["window", "target"], 2, "action", Bounded(-1.0, 1.0, shape=(1,)), [(1, 6, 6), (2,)]
)
SMALL = {"num_cells": [16, 16], "cnn_channels": [4], "cnn_kernels": [3], "cnn_strides": [2]}


def make(shared: bool = True, specs: StageSpecs = IMAGE, algo: str = "td3", **kw):
    if algo == "ddpg":
        cfg = DDPGConfig(**{**SMALL, "shared_encoder": shared, **kw})
        return DDPGLearner(OmegaConf.structured(cfg), specs)
    if algo == "sac":
        cfg = SACConfig(**{**SMALL, "shared_encoder": shared, **kw})
        return SACLearner(OmegaConf.structured(cfg), specs)
    cfg = TD3Config(**{**SMALL, "shared_encoder": shared, "policy_update_delay": 1, **kw})
    return TD3Learner(OmegaConf.structured(cfg), specs)


def batch(n: int = 32, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)

    def obs() -> dict[str, torch.Tensor]:
        window = (torch.rand(n, 1, 6, 6, generator=g) < 0.3).to(torch.uint8)
        return {"window": window, "target": torch.randn(n, 2, generator=g)}

    return TensorDict(
        **obs(),
        action=torch.rand(n, 1, generator=g) * 2 - 1,
        next=TensorDict(
            **obs(),
            reward=torch.randn(n, 1, generator=g),
            done=torch.rand(n, 1, generator=g) < 0.2,
            terminated=torch.rand(n, 1, generator=g) < 0.2,
            batch_size=[n],
        ),
        batch_size=[n],
    )


def encoder_params(learner: TD3Learner) -> list[torch.Tensor]:
    return list(learner.actor_module.encoder.parameters())


def critic(learner: TD3Learner, heads, i: int, encoder, *inputs: torch.Tensor) -> torch.Tensor:
    """``Q_i`` through the whole critic module: head ``i`` of ``heads`` on ``encoder``."""
    params = {f"body.{n}": p[i] for n, p in heads.flatten_keys(".").items()}
    params |= {f"encoder.{n}": p for n, p in encoder.items()}
    return functional_call(learner.critic_module, params, inputs)


def trained(**kw):
    learner = make(**kw)
    for seed in range(3):  # moves the targets away from the online networks
        learner.update(batch(seed=seed + 1))
    return learner


@pytest.mark.parametrize("algo", ["ddpg", "td3", "sac"])
def test_one_encoder_serves_the_actor_and_the_critics(algo):
    learner, separate = make(algo=algo), make(shared=False, algo=algo)
    assert learner.shared_encoder and not separate.shared_encoder
    assert learner.critic_module.encoder is learner.actor_module.encoder
    critic = "value_network" if algo == "ddpg" else "qvalue_network"
    for name in (f"{critic}_params", f"target_{critic}_params"):
        assert list(getattr(learner.loss, name)["module"].keys()) == ["body"]  # no copies
    # the critic optimizer trains the encoder, the actor optimizer does not
    actor, critics = learner.loss_parameters()
    ids = {id(p) for p in encoder_params(learner)}
    assert ids <= {id(p) for p in critics} and not ids & {id(p) for p in actor}
    total = sum(p.numel() for p in actor + critics)
    assert total < sum(p.numel() for group in separate.loss_parameters() for p in group)


def test_without_an_encoder_nothing_is_shared():
    vector = StageSpecs(["observation"], 3, "action", Bounded(-1.0, 1.0, shape=(1,)))
    assert not make(specs=vector).shared_encoder
    assert make(specs=vector, fourier_features=2).shared_encoder  # Fourier features: an encoder


def test_value_loss_is_td3s_on_the_shared_encoders():
    learner, data = trained(), batch()
    loss, cfg = learner.loss, learner.cfg
    obs, next_obs = learner.inputs(data), learner.inputs(data, nxt=True)
    online = dict(learner.actor_module.encoder.named_parameters())
    target = loss.target_actor_network_params["module", "0", "module", "encoder"]
    target = dict(target.flatten_keys(".").items())
    action = data["action"]
    torch.manual_seed(5)
    noise = (torch.randn_like(action) * cfg.policy_noise).clamp(-cfg.noise_clip, cfg.noise_clip)
    with torch.no_grad():
        next_action = (learner.squash(learner._target_actor(*next_obs)) + noise).clamp(-1, 1)
        heads = loss.target_qvalue_network_params["module", "body"]
        q_next = [critic(learner, heads, i, target, *next_obs, next_action) for i in (0, 1)]
        q_next = torch.stack(q_next)
        next_td = data["next"]
        y = next_td["reward"] + cfg.gamma * (~next_td["terminated"]) * q_next.min(0).values
    heads = loss.qvalue_network_params["module", "body"]
    reference = sum(
        (critic(learner, heads, i, online, *obs, action) - y).pow(2).mean() for i in (0, 1)
    )
    reference.backward()
    params = encoder_params(learner) + list(heads.values(True, True))
    expected = [p.grad.clone() for p in params]
    for p in params:
        p.grad = None
    torch.manual_seed(5)
    shared = learner._plain_value_loss(data.clone())
    shared.backward()
    torch.testing.assert_close(shared, reference)
    for p, grad in zip(params, expected, strict=True):
        torch.testing.assert_close(p.grad, grad, rtol=1e-4, atol=1e-6)


def test_actor_loss_trains_the_actor_head_only():
    learner, data = trained(), batch()
    obs = learner.inputs(data)
    heads = learner.loss.qvalue_network_params["module", "body"].detach()
    online = {n: p.detach() for n, p in learner.actor_module.encoder.named_parameters()}
    u = learner.actor_module(*obs)
    reference = -critic(learner, heads, 0, online, *obs, learner.squash(u)).mean()
    reference.backward()
    body = list(learner.actor_module.body.parameters())
    expected = [p.grad.clone() for p in body]
    learner.zero_grad(set_to_none=True)
    actor, penalty = learner._plain_actor_loss(data.clone())
    (actor + penalty).backward()
    torch.testing.assert_close(actor, reference)
    for p, grad in zip(body, expected, strict=True):
        torch.testing.assert_close(p.grad, grad, rtol=1e-4, atol=1e-6)
    assert all(p.grad is None for p in encoder_params(learner))
    assert all(p.grad is None for p in learner.loss.qvalue_network_params.values(True, True))

    before = [p.detach().clone() for p in encoder_params(learner)]
    learner.update(data.clone())  # the critic step moves the encoder
    assert all(not torch.equal(a, p) for a, p in zip(before, encoder_params(learner), strict=True))


@pytest.mark.parametrize("live", [False, True])
def test_stage_value_reads_the_target_encoder(live):
    learner = trained(tau=0.3)
    loss = learner.loss
    target = loss.target_actor_network_params["module", "0", "module", "encoder"]
    online = loss.actor_network_params["module", "0", "module", "encoder"]
    assert not (target == online.data).all()
    target = dict(target.flatten_keys(".").items())
    obs = batch().select("window", "target")
    value = learner.value(live=live)(obs.clone())["state_value"]
    inputs = (obs["window"], obs["target"])
    with torch.no_grad():
        action = learner.squash(learner._target_actor(*inputs))
        heads = loss.target_qvalue_network_params["module", "body"]
        q = torch.stack([critic(learner, heads, i, target, *inputs, action) for i in (0, 1)])
    torch.testing.assert_close(value, q.amin(0))


@pytest.mark.parametrize("algo", ["ddpg", "td3", "sac"])
def test_checkpoint_round_trip_continues_exactly(algo):
    trained = make(algo=algo)
    for seed in range(3):
        trained.update(batch(seed=seed))
    buffer = io.BytesIO()
    torch.save(trained.checkpoint(), buffer)
    buffer.seek(0)
    torch.manual_seed(123)  # other initial weights
    fresh = make(algo=algo)
    fresh.load_checkpoint(torch.load(buffer, weights_only=True))
    want, got = trained.state_dict(), fresh.state_dict()
    assert want.keys() == got.keys()
    assert all(torch.equal(want[k], got[k]) for k in want)
    assert fresh.critic_module.encoder is fresh.actor_module.encoder
    for learner in (trained, fresh):
        torch.manual_seed(7)
        learner.update(batch(seed=9))
    want, got = trained.state_dict(), fresh.state_dict()
    assert all(torch.equal(want[k], got[k]) for k in want)


def test_ddpg_losses_on_the_shared_encoder():
    learner, data = trained(algo="ddpg"), batch()
    loss, gamma = learner.loss, learner.cfg.gamma
    obs, next_obs = learner.inputs(data), learner.inputs(data, nxt=True)
    online = dict(learner.actor_module.encoder.named_parameters())
    target = loss.target_actor_network_params["module", "0", "module", "encoder"]
    target = dict(target.flatten_keys(".").items())
    heads = loss.value_network_params["module", "body"].unsqueeze(0)
    with torch.no_grad():
        next_action = learner.squash(learner._target_actor(*next_obs))
        target_heads = loss.target_value_network_params["module", "body"].unsqueeze(0)
        q_next = critic(learner, target_heads, 0, target, *next_obs, next_action)
        y = data["next", "reward"] + gamma * (~data["next", "terminated"]) * q_next
    loss_value = (critic(learner, heads, 0, online, *obs, data["action"]) - y).pow(2).mean()
    detached = {n: p.detach() for n, p in online.items()}
    u = functional_call(
        learner.actor_module, {f"encoder.{n}": p for n, p in detached.items()}, tuple(obs)
    )
    loss_actor = -critic(learner, heads.detach(), 0, detached, *obs, learner.squash(u)).mean()
    (loss_actor + loss_value).backward()
    params = list(learner.actor_module.parameters()) + list(learner.critic_module.body.parameters())
    expected = [p.grad.clone() for p in params]
    learner.zero_grad(set_to_none=True)
    actor, value, penalty = learner._plain_losses(data.clone())
    (actor + value + penalty).backward()
    torch.testing.assert_close(actor, loss_actor)
    torch.testing.assert_close(value, loss_value)
    for p, grad in zip(params, expected, strict=True):  # the encoder's from the critic alone
        torch.testing.assert_close(p.grad, grad, rtol=1e-4, atol=1e-6)
    obs_td = batch().select("window", "target")
    with torch.no_grad():
        action = learner.squash(learner._target_actor(*obs_td.values()))
        want = critic(learner, target_heads, 0, target, *obs_td.values(), action)
    torch.testing.assert_close(learner.value()(obs_td)["state_value"], want)


def test_sac_losses_on_the_shared_encoder():
    """SAC's losses through the whole critic modules (the trained encoder for s, the target
    one for the target critics at s'), the actor on detached features: the same values and
    gradients, the encoder's from the critics' loss alone."""
    from torchrl.modules import TanhNormal
    from torchrl.modules.distributions.utils import rsample_and_log_prob

    learner, data = trained(algo="sac"), batch()
    loss, gamma = learner.loss, learner.cfg.gamma
    obs, next_obs = learner.inputs(data), learner.inputs(data, nxt=True)
    online = dict(learner.actor_module.encoder.named_parameters())
    target = loss.target_actor_network_params["module", "0", "module", "0", "encoder"]
    target = dict(target.flatten_keys(".").items())
    kwargs = learner.actor[1].distribution_kwargs
    alpha = loss.log_alpha.detach().exp()

    def policy(out):
        loc, scale = learner.actor[0].module[1](out)
        return rsample_and_log_prob(TanhNormal(loc, scale, **kwargs))

    torch.manual_seed(5)
    with torch.no_grad():
        next_action, next_lp = policy(learner.actor_module(*next_obs))
        heads = loss.target_qvalue_network_params["module", "body"]
        q_next = [critic(learner, heads, i, target, *next_obs, next_action) for i in (0, 1)]
        soft = (torch.stack(q_next) - alpha * next_lp.unsqueeze(-1)).min(0).values
        y = data["next", "reward"] + gamma * (~data["next", "terminated"]) * soft
    heads = loss.qvalue_network_params["module", "body"]
    loss_q = sum(
        (critic(learner, heads, i, online, *obs, data["action"]) - y).pow(2).mean() for i in (0, 1)
    )
    detached = {n: p.detach() for n, p in online.items()}
    encoded = {f"encoder.{n}": p for n, p in detached.items()}
    action, lp = policy(functional_call(learner.actor_module, encoded, tuple(obs)))
    q = [critic(learner, heads.detach(), i, detached, *obs, action) for i in (0, 1)]
    loss_actor = (alpha * lp - torch.stack(q).min(0).values.squeeze(-1)).mean()
    loss_alpha = (-loss.log_alpha * (lp.detach() + loss.target_entropy)).mean()
    (loss_actor + loss_q + loss_alpha).backward()
    params = [*learner.actor_module.parameters(), *heads.values(True, True), loss.log_alpha]
    expected = [p.grad.clone() for p in params]
    learner.zero_grad(set_to_none=True)
    loss.log_alpha.grad = None
    torch.manual_seed(5)
    got = learner._plain_losses(data.clone())
    sum(got).backward()
    for value, want in zip(got, (loss_actor, loss_q, loss_alpha), strict=True):
        torch.testing.assert_close(value, want)
    for p, grad in zip(params, expected, strict=True):  # the encoder's from the critics alone
        torch.testing.assert_close(p.grad, grad, rtol=1e-4, atol=1e-6)
