"""Per-stage learners (DQN, DDPG, TD3) behind the Learner interface, and a small end-to-end run of
the backward schedule that must find the optimal whole-task paths."""

import copy
import io
import warnings

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, OneHot

from torchrl_stages.evaluate import evaluate_policy
from torchrl_stages.learners import ALGORITHMS, StageSpecs, make_learner
from torchrl_stages.learners.ddpg import DDPGConfig, DDPGLearner
from torchrl_stages.learners.dqn import DQNConfig, DQNLearner
from torchrl_stages.learners.td3 import TD3Config, TD3Learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.schedules import train_backward
from torchrl_stages.task import StagedTask
from torchrl_stages.values import with_params

OBS_DIM, NUM_ACTIONS, ACTION_DIM = 3, 4, 2
SMALL = {"num_cells": [16, 16], "lr": 1e-2, "tau": 0.1, "annealing_frames": 1000}


def dqn_cfg(**kw):
    return OmegaConf.structured(DQNConfig(**{**SMALL, **kw}))


def ddpg_cfg(**kw):
    return OmegaConf.structured(DDPGConfig(**{**SMALL, "actor_lr": 1e-2, **kw}))


def td3_cfg(**kw):
    return OmegaConf.structured(TD3Config(**{**SMALL, "actor_lr": 1e-2, **kw}))


DISCRETE = StageSpecs(["observation"], OBS_DIM, "action", Categorical(NUM_ACTIONS))
CONTINUOUS = StageSpecs(["observation"], OBS_DIM, "action", Bounded(-1.0, 1.0, shape=(ACTION_DIM,)))

ALGOS = {
    "dqn": (DQNLearner, dqn_cfg, DISCRETE),
    "ddpg": (DDPGLearner, ddpg_cfg, CONTINUOUS),
    "td3": (TD3Learner, td3_cfg, CONTINUOUS),
}


def make(algo, **kw):
    cls, cfg_fn, specs = ALGOS[algo]
    return cls(cfg_fn(**kw), specs)


def batch_for(specs: StageSpecs, n=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    if isinstance(specs.action_spec, Categorical):
        action = torch.randint(specs.action_spec.space.n, (n,), generator=g)
    else:
        action = torch.rand(n, *specs.action_spec.shape, generator=g) * 2 - 1
    return TensorDict(
        observation=torch.randn(n, specs.observation_dim, generator=g),
        action=action,
        next=TensorDict(
            observation=torch.randn(n, specs.observation_dim, generator=g),
            reward=torch.randn(n, 1, generator=g),
            done=torch.rand(n, 1, generator=g) < 0.2,
            terminated=torch.rand(n, 1, generator=g) < 0.2,
            batch_size=[n],
        ),
        batch_size=[n],
    )


def snapshot(learner):
    return {k: v.detach().clone() for k, v in learner.state_dict().items()}


def loss_params(learner, prefix: str = "") -> dict:
    """Copies of the loss's online parameters (its targets' with ``prefix="target_"``)."""
    nets = {"dqn": ["value"], "ddpg": ["actor", "value"], "td3": ["actor", "qvalue"]}[learner.algo]
    names = [f"{prefix}{net}_network_params" for net in nets]
    return {n: getattr(learner.loss, n).detach().clone() for n in names}


def td_equal(a, b):
    return all(torch.equal(a[k], b[k]) for k in a.keys(True, True))


# ---------------------------------------------------------------------- registry
def test_registry_and_make_learner():
    assert {"dqn", "ddpg", "td3"} <= set(ALGORITHMS)
    assert isinstance(make_learner(dqn_cfg(), DISCRETE), DQNLearner)
    assert isinstance(make_learner(ddpg_cfg(), CONTINUOUS), DDPGLearner)
    assert isinstance(make_learner(td3_cfg(), CONTINUOUS), TD3Learner)


# ---------------------------------------------------------------------- update
@pytest.mark.parametrize("algo", list(ALGOS))
def test_fused_adam_makes_the_same_updates_up_to_rounding(algo):
    learners = {}
    for fused in (False, True):
        torch.manual_seed(0)
        learner = make(algo, fused_adam=fused)
        for i in range(5):
            torch.manual_seed(i)  # TD3's smoothing noise
            learner.update(batch_for(learner.specs, seed=i))
        learners[fused] = learner
    assert all(o.defaults["fused"] for o in learners[True].optimizers.values())
    assert not any(o.defaults["fused"] for o in learners[False].optimizers.values())
    plain, fused = snapshot(learners[False]), snapshot(learners[True])
    for name, value in plain.items():
        assert torch.allclose(value, fused[name], atol=1e-5), name
    # checkpoints are portable between the two: each loads the other's and steps on
    plain_state, fused_state = learners[False].checkpoint(), learners[True].checkpoint()
    learners[False].load_checkpoint(fused_state)
    learners[True].load_checkpoint(plain_state)
    for learner in learners.values():
        learner.update(batch_for(learner.specs, seed=9))
        assert all(torch.isfinite(v).all() for v in snapshot(learner).values())


def _adam_pair(**kw):
    """Two copies of a small network, one under torch's fused Adam, one under FusedAdam."""
    from torchrl_stages.learners.ops import FusedAdam

    torch.manual_seed(0)
    nets = [torch.nn.Sequential(torch.nn.Linear(5, 8), torch.nn.ReLU(), torch.nn.Linear(8, 2))]
    nets.append(copy.deepcopy(nets[0]))
    kw = {"lr": 1e-2, **kw}
    reference = torch.optim.Adam(nets[0].parameters(), fused=True, **kw)
    return nets, reference, FusedAdam(nets[1].parameters(), **kw)


def _adam_steps(nets, optimizers, steps=6):
    for i in range(steps):
        x = torch.randn(16, 5, generator=torch.Generator().manual_seed(i))
        for net, optimizer in zip(nets, optimizers, strict=True):
            net(x).pow(2).mean().backward()
            step = getattr(optimizer, "direct_step", optimizer.step)
            step()
            optimizer.zero_grad(set_to_none=True)
            for group in optimizer.param_groups:
                group["lr"] *= 0.9  # the stage loop's learning-rate decay


@pytest.mark.parametrize("kw", [{}, {"weight_decay": 0.1, "betas": (0.8, 0.99), "eps": 1e-6}])
def test_fused_adam_direct_step_is_torchs_fused_adam_bit_for_bit(kw):
    nets, reference, direct = _adam_pair(**kw)
    calls, adam_steps = [], []
    kernel, adam_step = torch._fused_adam_, direct.step
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(torch, "_fused_adam_", lambda *a, **k: calls.append(1) or kernel(*a, **k))
        patch.setattr(direct, "step", lambda: adam_steps.append(1) or adam_step())
        _adam_steps(nets, [reference, direct])
    assert len(calls) == 2 * 6  # both optimizers ran the kernel at every step
    assert len(adam_steps) == 1  # Adam.step only for the first (it creates the state)
    for a, b in zip(nets[0].parameters(), nets[1].parameters(), strict=True):
        assert torch.equal(a, b)
    for a, b in zip(reference.state.values(), direct.state.values(), strict=True):
        assert all(torch.equal(a[k], b[k]) for k in a)
    # the state is Adam's: each loads the other's and both go on equally
    direct.load_state_dict(copy.deepcopy(reference.state_dict()))
    _adam_steps(nets, [reference, direct], steps=2)
    pairs = zip(nets[0].parameters(), nets[1].parameters(), strict=True)
    assert all(torch.equal(a, b) for a, b in pairs)


def test_fused_adam_direct_step_runs_adam_step_where_it_must():
    """Hooks, a parameter without a gradient or an AMSGrad group: ``Adam.step`` itself."""
    nets, _, direct = _adam_pair()
    _adam_steps([nets[1]], [direct], steps=1)
    seen = []
    handle = direct.register_step_post_hook(lambda *a: seen.append(1))
    _adam_steps([nets[1]], [direct], steps=2)
    assert seen == [1, 1]  # once per step, not skipped nor doubled
    handle.remove()
    nets[1][0].weight.requires_grad_(False)  # no gradient for one parameter
    before = nets[1][2].weight.clone()
    _adam_steps([nets[1]], [direct], steps=1)
    assert not torch.equal(before, nets[1][2].weight)
    for kw in ({"amsgrad": True}, {"maximize": True}, {"lr": torch.tensor(1e-2)}):
        nets, _, other = _adam_pair(**kw)
        _adam_steps([nets[1]], [other], steps=1)
        assert not other._direct(), kw
    # the state of a non-fused Adam turns fused off: direct_step is then that Adam's step
    nets, _, direct = _adam_pair()
    plain = torch.optim.Adam(nets[0].parameters(), lr=1e-2)
    _adam_steps([nets[0]], [plain], steps=2)
    nets[1].load_state_dict(nets[0].state_dict())
    direct.load_state_dict(copy.deepcopy(plain.state_dict()))
    assert not direct._direct()
    _adam_steps(nets, [plain, direct], steps=2)
    pairs = zip(nets[0].parameters(), nets[1].parameters(), strict=True)
    assert all(torch.equal(a, b) for a, b in pairs)
    # an empty parameter group is skipped, as Adam.step skips it
    nets, reference, direct = _adam_pair()
    for optimizer in (reference, direct):
        optimizer.add_param_group({"params": []})
    _adam_steps(nets, [reference, direct], steps=3)
    pairs = zip(nets[0].parameters(), nets[1].parameters(), strict=True)
    assert all(torch.equal(a, b) for a, b in pairs)


def test_total_grad_norm_is_torchs_total_norm():
    from torchrl_stages.learners.ops import total_grad_norm

    grads = [torch.randn(64, 14), torch.randn(64), torch.randn(4, 64), torch.randn(1)]
    assert torch.equal(total_grad_norm(grads), torch.nn.utils.get_total_norm(grads))
    mixed = [grads[0], grads[1].double()]  # two dtypes: torch's own grouping
    assert torch.equal(total_grad_norm(mixed), torch.nn.utils.get_total_norm(mixed))
    assert total_grad_norm([]).item() == 0.0


@pytest.mark.parametrize("algo", list(ALGOS))
def test_only_td3_updates_draw_random_numbers(algo):
    """The stage loop draws a batch's minibatches at once for learners whose update leaves
    torch's generator alone (``update_draws_random`` false): it must be true of them."""
    learner = make(algo)
    batch = batch_for(learner.specs)
    learner.update(batch.clone())  # past any first-call setup
    for _ in range(2):  # the TD3 actor's delayed update included
        state = torch.get_rng_state()
        learner.update(batch.clone())
        drew = not torch.equal(state, torch.get_rng_state())
        assert drew == learner.update_draws_random == (algo == "td3")


@pytest.mark.parametrize("algo", list(ALGOS))
def test_updates_change_parameters_and_return_finite_losses(algo):
    learner = make(algo, policy_update_delay=2) if algo == "td3" else make(algo)
    online0, target0 = loss_params(learner), loss_params(learner, "target_")
    batch = batch_for(learner.specs)
    all_keys = set()
    for i in range(4):
        losses = learner.update(batch.clone())
        assert losses, "update returned no loss"
        for name, value in losses.items():
            assert value.ndim == 0 and torch.isfinite(value), name
            assert not value.requires_grad
        all_keys |= set(losses)
        assert learner.num_updates == i + 1
    expected_keys = {
        "dqn": {"loss", "grad_norm"},
        "ddpg": {"loss_actor", "loss_value", "grad_norm_actor", "grad_norm_critic"},
        "td3": {"loss_qvalue", "loss_actor", "grad_norm_actor", "grad_norm_critic"},
    }[algo]
    assert all_keys == expected_keys
    for name, before in online0.items():
        after = getattr(learner.loss, name)
        assert not td_equal(before, after.detach()), f"{name} did not change"
    for name, before in target0.items():
        after = getattr(learner.loss, name)
        assert not td_equal(before, after.detach()), f"{name} did not move (target update)"
    # the greedy policy acts with the updated online networks
    for name, online in loss_params(learner).items():
        assert all(torch.isfinite(t).all() for t in online.values(True, True)), name


@pytest.mark.parametrize("algo", list(ALGOS))
def test_a_learner_moves_like_any_module(algo):
    learner = make(algo)
    assert learner.to("cpu", torch.float32) is learner  # nn.Module.to, through nn.Module._apply
    assert learner.update(batch_for(learner.specs))


def test_td3_actor_and_targets_update_every_policy_update_delay():
    learner = make("td3", policy_update_delay=3)
    batch = batch_for(CONTINUOUS)
    actor0 = learner.loss.actor_network_params.detach().clone()
    target0 = learner.loss.target_qvalue_network_params.detach().clone()
    keys = [set(learner.update(batch.clone())) for _ in range(3)]
    critic = {"loss_qvalue", "grad_norm_critic"}
    assert keys == [critic, critic, critic | {"loss_actor", "grad_norm_actor"}]
    assert not td_equal(actor0, learner.loss.actor_network_params.detach())
    assert not td_equal(target0, learner.loss.target_qvalue_network_params.detach())


def test_td3_no_target_update_before_delay():
    learner = make("td3", policy_update_delay=2)
    target0 = learner.loss.target_qvalue_network_params.detach().clone()
    actor0 = learner.loss.actor_network_params.detach().clone()
    learner.update(batch_for(CONTINUOUS))
    assert td_equal(target0, learner.loss.target_qvalue_network_params.detach())
    assert td_equal(actor0, learner.loss.actor_network_params.detach())


def saturate(learner, bias: float) -> None:
    """Pushes every pre-tanh actor output to about ``bias`` (deep saturation for |bias| >> 2)."""
    last = [m for m in learner.actor.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(bias)


@pytest.mark.parametrize("algo", ["ddpg", "td3"])
def test_saturation_penalty_is_zero_inside_the_bound(algo):
    learner = make(algo, saturation_penalty=1.0)
    saturate(learner, 1.5)
    penalty = learner.penalty(learner.actor_module(*learner.inputs(batch_for(learner.specs))))
    assert penalty.item() == 0.0
    off = make(algo, saturation_penalty=0.0)
    nothing = off.penalty(off.actor_module(*off.inputs(batch_for(off.specs))))
    assert nothing == 0.0  # 0 adds nothing


@pytest.mark.parametrize("algo", ["ddpg", "td3"])
def test_saturation_penalty_pulls_a_saturated_actor_back(algo):
    learner = (
        make(algo, saturation_penalty=1.0, policy_update_delay=1)
        if algo == "td3"
        else (make(algo, saturation_penalty=1.0))
    )
    saturate(learner, 6.0)  # tanh'(6) = 2.5e-5: the actor loss alone barely moves it
    batch = batch_for(learner.specs)
    penalty = learner.penalty(learner.actor_module(*learner.inputs(batch)))
    assert penalty.item() == pytest.approx((6.0 - 2.0) ** 2, rel=1e-5)
    last = [m for m in learner.actor.modules() if isinstance(m, torch.nn.Linear)][-1]
    for _ in range(20):
        learner.update(batch)
    assert (last.bias < 6.0 - 20 * 1e-2 * 0.5).all()  # Adam steps of ~lr towards the bound


@pytest.mark.parametrize("double", [False, True])
def test_double_dqn_switch_picks_the_bootstrap_action(double):
    learner = DQNLearner(dqn_cfg(double_dqn=double), DISCRETE)
    assert learner.loss.double_dqn is double
    batch = batch_for(DISCRETE)
    with torch.no_grad():  # online and target networks disagree on argmax_a' Q(s', a')
        for p in learner.loss.target_value_network_params.values(True, True):
            p.add_(0.5 * torch.randn_like(p))
    online = learner.qnet
    target = with_params(learner.qnet, learner.loss.target_value_network_params)
    with torch.no_grad():
        q_online = online(batch["next"].clone())["action_value"]
        q_target = target(batch["next"].clone())["action_value"]
        plain = q_target.max(-1, keepdim=True).values
        double_q = q_target.gather(-1, q_online.argmax(-1, keepdim=True))
        assert not torch.allclose(plain, double_q)
        q_sa = online(batch.clone())["action_value"].gather(-1, batch["action"].unsqueeze(-1))

    def mse(bootstrap):
        alive = (~batch["next", "terminated"]).float()
        y = batch["next", "reward"] + learner.cfg.gamma * bootstrap * alive
        return (q_sa - y).pow(2).mean()

    loss = learner.loss(batch.clone())["loss"].detach()
    torch.testing.assert_close(loss, mse(double_q if double else plain))
    assert not torch.allclose(loss, mse(plain if double else double_q))


def test_dqn_double_and_dueling_build_and_update():
    learner = DQNLearner(dqn_cfg(double_dqn=True, dueling=True), DISCRETE)
    assert learner.loss.double_dqn
    plain = DQNLearner(dqn_cfg(dueling=False), DISCRETE)
    names = {n for n, _ in learner.qnet.named_parameters()}
    assert names != {n for n, _ in plain.qnet.named_parameters()}  # a different (dueling) net
    online0 = loss_params(learner)
    batch = batch_for(DISCRETE)
    for _ in range(3):
        losses = learner.update(batch.clone())
        assert torch.isfinite(losses["loss"])
    assert not td_equal(online0["value_network_params"], learner.loss.value_network_params.data)
    out = learner.policy(TensorDict(observation=torch.randn(5, OBS_DIM), batch_size=[5]))
    assert out["action_value"].shape == (5, NUM_ACTIONS)
    assert out["action"].shape == (5,)
    value = learner.value()(TensorDict(observation=torch.randn(5, OBS_DIM), batch_size=[5]))
    assert value["state_value"].shape == (5, 1)


@pytest.mark.parametrize("alpha", [0.0, 0.9])
@pytest.mark.parametrize("dtype", [torch.long, torch.bool])
def test_dqn_one_hot_actions_give_the_loss_of_their_indices(alpha, dtype):
    specs = StageSpecs(["observation"], OBS_DIM, "action", OneHot(NUM_ACTIONS))
    torch.manual_seed(0)
    learner = DQNLearner(dqn_cfg(advantage_learning=alpha), specs)
    torch.manual_seed(0)
    indexed = DQNLearner(dqn_cfg(advantage_learning=alpha), DISCRETE)
    batch = batch_for(DISCRETE)
    expected = indexed._plain_loss(batch.clone())
    batch["action"] = torch.nn.functional.one_hot(batch["action"], NUM_ACTIONS).to(dtype)
    torch.testing.assert_close(learner._plain_loss(batch.clone()), expected)
    assert torch.isfinite(learner.update(batch)["loss"])


# ---------------------------------------------------------------------- annealing
@pytest.mark.parametrize(
    ("frames", "expected"), [(0, 1.0), (250, 0.7625), (500, 0.525), (1000, 0.05), (5000, 0.05)]
)
def test_dqn_anneal_epsilon(frames, expected):
    learner = make("dqn", eps_init=1.0, eps_end=0.05, annealing_frames=1000)
    learner.anneal(frames)
    assert learner.egreedy.eps.item() == pytest.approx(expected)


@pytest.mark.parametrize("algo", ["ddpg", "td3"])
@pytest.mark.parametrize(
    ("frames", "expected"), [(0, 0.5), (100, 0.42), (250, 0.3), (500, 0.1), (10_000, 0.1)]
)
def test_actor_critic_anneal_sigma(algo, frames, expected):
    learner = make(algo, sigma_init=0.5, sigma_end=0.1, annealing_frames=500)
    learner.anneal(frames)
    assert learner.noise.sigma.item() == pytest.approx(expected)


def test_dqn_accepts_integer_exploration_values():
    # plain dataclass configs (not OmegaConf-typed) may carry ints: no torchrl warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        learner = DQNLearner(DQNConfig(eps_init=1, eps_end=0, num_cells=[8]), DISCRETE)
    learner.anneal(0)
    assert learner.egreedy.eps.item() == 1.0


@pytest.mark.parametrize("cfg_cls", [DDPGConfig, TD3Config])
def test_actor_critic_accepts_integer_exploration_values(cfg_cls):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        learner = make_learner(cfg_cls(sigma_init=1, sigma_end=0, num_cells=[8]), CONTINUOUS)
    learner.anneal(0)
    assert learner.noise.sigma.item() == 1.0


def test_anneal_without_horizon_is_the_end_value():
    learner = make("dqn", eps_init=1.0, eps_end=0.2, annealing_frames=0)
    learner.anneal(0)
    assert learner.egreedy.eps.item() == pytest.approx(0.2)


def test_anneal_is_not_cumulative():
    learner = make("dqn", eps_init=1.0, eps_end=0.0, annealing_frames=100)
    learner.anneal(80)
    learner.anneal(50)
    assert learner.egreedy.eps.item() == pytest.approx(0.5)


# ---------------------------------------------------------------------- checkpoints
@pytest.mark.parametrize("algo", list(ALGOS))
def test_checkpoint_round_trip(algo):
    trained = make(algo, policy_update_delay=1) if algo == "td3" else make(algo)
    batch = batch_for(trained.specs)
    for _ in range(3):
        trained.update(batch.clone())
    trained.anneal(400)
    buf = io.BytesIO()
    torch.save(trained.checkpoint(), buf)
    buf.seek(0)
    state = torch.load(buf, weights_only=True)

    torch.manual_seed(123)  # different initial weights
    fresh = make(algo, policy_update_delay=1) if algo == "td3" else make(algo)
    assert not td_equal(
        loss_params(fresh)[next(iter(loss_params(fresh)))],
        loss_params(trained)[next(iter(loss_params(trained)))],
    )
    fresh.load_checkpoint(state)

    # weights, target weights, exploration state
    want, got = snapshot(trained), snapshot(fresh)
    assert want.keys() == got.keys()
    for key in want:
        assert torch.equal(want[key], got[key]), key
    for name, params in loss_params(trained, "target_").items():
        assert td_equal(params, getattr(fresh.loss, name).detach()), name
    for name, params in loss_params(trained).items():
        assert td_equal(params, getattr(fresh.loss, name).detach()), name
    assert fresh.num_updates == trained.num_updates == 3
    # optimizer states (Adam moments and step counts)
    assert trained.optimizers.keys() == fresh.optimizers.keys()
    for name, opt in trained.optimizers.items():
        s_want, s_got = opt.state_dict(), fresh.optimizers[name].state_dict()
        assert s_want["param_groups"] == s_got["param_groups"]
        assert s_want["state"].keys() == s_got["state"].keys() and s_want["state"]
        for idx, entry in s_want["state"].items():
            for k, v in entry.items():
                assert torch.equal(v, s_got["state"][idx][k]), (name, idx, k)
    # the restored optimizer continues exactly like the original one
    next_batch = batch_for(trained.specs, seed=1)
    torch.manual_seed(7)
    trained.update(next_batch.clone())
    torch.manual_seed(7)
    fresh.update(next_batch.clone())
    want, got = snapshot(trained), snapshot(fresh)
    for key in want:
        assert torch.allclose(want[key], got[key], atol=1e-6), key
    # the greedy policy acts identically
    obs = TensorDict(observation=torch.randn(6, OBS_DIM), batch_size=[6])
    assert torch.equal(trained.policy(obs.clone())["action"], fresh.policy(obs.clone())["action"])


def test_checkpoint_restores_exploration_state():
    trained = make("dqn")
    trained.anneal(500)
    fresh = make("dqn")
    assert fresh.egreedy.eps.item() == pytest.approx(1.0)
    fresh.load_checkpoint(trained.checkpoint())
    assert fresh.egreedy.eps.item() == pytest.approx(trained.egreedy.eps.item())


# ---------------------------------------------------------------------- action-space checks
@pytest.mark.parametrize("spec", [Bounded(-1.0, 1.0, shape=(2,)), Bounded(-1.0, 1.0, shape=(1,))])
def test_dqn_rejects_continuous_actions(spec):
    problem = DQNLearner.check_action_spec(spec)
    assert problem is not None and "discrete" in problem


@pytest.mark.parametrize("cls", [DDPGLearner, TD3Learner])
@pytest.mark.parametrize("spec", [Categorical(4), OneHot(4)])
def test_actor_critic_rejects_discrete_actions(cls, spec):
    problem = cls.check_action_spec(spec)
    assert problem is not None and "continuous" in problem


def test_matching_action_specs_are_accepted():
    assert DQNLearner.check_action_spec(Categorical(4)) is None
    assert DQNLearner.check_action_spec(OneHot(4)) is None
    for cls in (DDPGLearner, TD3Learner):
        assert cls.check_action_spec(Bounded(-1.0, 1.0, shape=(2,))) is None


# ---------------------------------------------------------------------- it learns
def toy_task(overrides=None):
    """4x4 grid, two strips of width 2, target (3, 3). With this budget (1536 frames per stage)
    the greedy stacked policy was optimal from every cell for 40 seeds out of 40 (1024 frames:
    30/30 seeds; 512 frames: 5/10); one run takes about 2-3 s on one CPU thread."""
    stage = {
        "num_envs": 16,
        "frames": 1536,
        "frames_per_batch": 64,
        "init_random_frames": 128,
        "batch_size": 128,
        "buffer_size": 10_000,
        "tau": 0.05,
        "lr": 2e-3,
        "updates_per_batch": 8,
        "eval_every": 0,
        "gamma": 0.9,
        "num_cells": [32, 32],
        "annealing_frames": 768,
        "eps_end": 0.05,
        **(overrides or {}),
    }
    cfg = OmegaConf.create(
        {
            "name": "toy",
            "env": {
                "_target_": "torchrl_stages.envs.GridWorldEnv",
                "size": 4,
                "num_stages": 2,
                "max_steps": 30,
            },
            "eval_env": {},
            "stages": {
                "s0": OmegaConf.structured(DQNConfig(**stage)),
                "s1": OmegaConf.structured(DQNConfig(**stage)),
            },
        }
    )
    return StagedTask(cfg)


def test_backward_schedule_learns_optimal_paths():
    task = toy_task()
    [run] = train_backward(task, [0])
    learners, results = run.learners, run.results
    assert [r.stage for r in results] == [0, 1]
    assert all(r.frames == 1536 for r in results)
    policy = StackedPolicy([learner.policy for learner in learners])
    env = task.task_env(4, start_cell=[[r, 0] for r in range(4)])
    stats, rollout = evaluate_policy(env, policy, 30)
    # optimal from (r, 0) to the target (3, 3): 3 moves right and 3 - r moves down
    assert stats.success.tolist() == [True] * 4
    assert stats.length.tolist() == [6, 5, 4, 3]
    assert stats.ret.tolist() == [1.0] * 4
    assert rollout["stage"][:, 0].squeeze(-1).tolist() == [0] * 4
    # every other start too: the path length is the Manhattan distance to the target
    cells = [[r, c] for r in range(4) for c in range(4) if (r, c) != (3, 3)]
    stats, _ = evaluate_policy(task.task_env(len(cells), start_cell=cells), policy, 30)
    assert stats.success.all()
    assert stats.length.tolist() == [(3 - r) + (3 - c) for r, c in cells]
