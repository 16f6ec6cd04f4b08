"""Several seeds in one process: seed-stacked learners, their replay storage, the envs with one
copy of the starts per seed, and ``stages-train seeds=[...]`` writing one run directory per
seed."""

from __future__ import annotations

import dataclasses
import io
import json
import logging
import math
import signal
import sys
from pathlib import Path

import pytest
import torch
from helpers import run_cli, tiny_grid, two_stage_grid
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical

from torchrl_stages import loop as loop_module
from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.config import ConfigError
from torchrl_stages.early_stop import SeedRow
from torchrl_stages.learners import StageSpecs, make_learner
from torchrl_stages.learners.ddpg import DDPGConfig
from torchrl_stages.learners.discrete_sac import DiscreteSACConfig
from torchrl_stages.learners.dqn import DQNConfig
from torchrl_stages.learners.networks import mlp
from torchrl_stages.learners.sac import SACConfig
from torchrl_stages.learners.stacking import (
    StackedConv2d,
    StackedLinear,
    stack_for_seeds,
    stack_learners,
    stacked_networks,
    unstack_learner,
    update_rows,
)
from torchrl_stages.learners.td3 import TD3Config
from torchrl_stages.loggers import RunLogger
from torchrl_stages.metrics import MetricsLog
from torchrl_stages.preemption import Interrupted
from torchrl_stages.replay import SeedReplayBuffer
from torchrl_stages.runs.experiment import Experiment, validate_seeds
from torchrl_stages.runs.loading import load_run
from torchrl_stages.schedules import backward as backward_module
from torchrl_stages.schedules import flat as flat_module
from torchrl_stages.schedules.backward import train_backward
from torchrl_stages.schedules.joint import JointSchedule, JointTrainer
from torchrl_stages.task import StagedTask, tile_starts

# a 1 x 6 x 6 occupancy image and a 2-vector, like the cargo stages' window and target
IMAGE = ["window", "target"], [(1, 6, 6), (2,)]
CNN = {"num_cells": [16, 16], "cnn_channels": [4], "cnn_kernels": [3], "cnn_strides": [2]}


def _obs(lead: tuple[int, ...], image: bool) -> dict[str, torch.Tensor]:
    if image:
        window = (torch.rand(*lead, 1, 6, 6) < 0.3).to(torch.uint8)
        return {"window": window, "target": torch.randn(*lead, 2)}
    return {"observation": torch.randn(*lead, 3)}


def _batch(lead: tuple[int, ...], action: torch.Tensor, image: bool = False) -> TensorDict:
    done = torch.zeros(*lead, 1, dtype=torch.bool)
    nxt = TensorDict(
        **_obs(lead, image),
        reward=torch.randn(*lead, 1),
        done=done,
        terminated=torch.rand(*lead, 1) < 0.2,
        batch_size=lead,
    )
    return TensorDict(**_obs(lead, image), action=action, next=nxt, batch_size=lead)


def _specs(algo: str) -> StageSpecs:
    spec = CASES[algo][1]
    if algo.endswith("cnn"):
        keys, shapes = IMAGE
        return StageSpecs(keys, 2, "action", spec, shapes)
    return StageSpecs(["observation"], 3, "action", spec)


CASES = {
    # gradient clipping on: each seed is clipped by its own norm
    "dqn": (
        DQNConfig(gamma=0.9, max_grad_norm=0.5, fourier_features=2),
        Categorical(4),
        lambda lead: torch.randint(0, 4, lead),
    ),
    "ddpg": (
        DDPGConfig(gamma=0.9, max_grad_norm=1.0),
        Bounded(-1, 1, (2,)),
        lambda lead: torch.rand(*lead, 2) * 2 - 1,
    ),
    # twin critics, stacked by the loss module on top of the seeds ([2, seeds, ...]); no
    # target smoothing noise, which the seeds would draw in another order
    "td3": (
        TD3Config(gamma=0.9, max_grad_norm=1.0, policy_noise=0.0, policy_update_delay=2),
        Bounded(-1, 1, (2,)),
        lambda lead: torch.rand(*lead, 2) * 2 - 1,
    ),
    # its target reads the target network at s too
    "dqn-advantage-learning": (
        DQNConfig(gamma=0.9, advantage_learning=0.9),
        Categorical(4),
        lambda lead: torch.randint(0, 4, lead),
    ),
    # image inputs: each seed's CNN in one grouped convolution
    "dqn-cnn": (
        DQNConfig(gamma=0.9, max_grad_norm=0.5, **CNN),
        Categorical(4),
        lambda lead: torch.randint(0, 4, lead),
    ),
    # the cargo slider's kind: one CNN shared by the actor and the critics
    "td3-shared-cnn": (
        TD3Config(gamma=0.9, policy_noise=0.0, shared_encoder=True, **CNN),
        Bounded(-1, 1, (1,)),
        lambda lead: torch.rand(*lead, 1) * 2 - 1,
    ),
    # one entropy coefficient per seed; the update's expectations are exact (no draws)
    "discrete_sac": (
        DiscreteSACConfig(gamma=0.9, max_grad_norm=1.0, alpha_lr=0.1),
        Categorical(4),
        lambda lead: torch.randint(0, 4, lead),
    ),
    # its update samples actions: the noise is injected (_same_noise_per_seed); its stage
    # value draws its own fixed noise, the same for each seed's block of states
    "sac": (
        SACConfig(gamma=0.9, max_grad_norm=1.0, alpha_lr=0.1, value_samples=4),
        Bounded(-1, 1, (2,)),
        lambda lead: torch.rand(*lead, 2) * 2 - 1,
    ),
    "sac-shared-cnn": (
        SACConfig(gamma=0.9, alpha_lr=0.1, shared_encoder=True, value_samples=4, **CNN),
        Bounded(-1, 1, (1,)),
        lambda lead: torch.rand(*lead, 1) * 2 - 1,
    ),
}


def _same_noise_per_seed(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every Gaussian draw of an update (SAC's actions) gets noise that depends on the
    position within a seed's batch alone, so that a stacked learner's seeds draw what their
    ordinary learners draw: a fixed pattern over a batch's last two dimensions (``[B, d]``),
    repeated over the seeds' (``[N, B, d]``)."""

    def pattern(shape, dtype=None, device=None) -> torch.Tensor:
        size = shape[-2] * shape[-1]
        noise = torch.sin(torch.arange(size, dtype=dtype, device=device) * 1.3 + 0.4) * 1.5
        return noise.reshape(shape[-2:]).expand(shape).clone()

    monkeypatch.setattr(torch.distributions.normal, "_standard_normal", pattern)


@pytest.mark.parametrize("algo", list(CASES))
def test_a_stacked_learner_updates_each_seed_as_its_own_learner_would(algo, monkeypatch):
    _same_noise_per_seed(monkeypatch)
    cfg, _, action = CASES[algo]
    specs, image = _specs(algo), algo.endswith("cnn")
    n, size = 3, 16
    singles = [make_learner(cfg, specs) for _ in range(n)]
    stacked = stack_learners(make_learner(cfg, specs, seeds=n), singles)
    for step in range(4):
        batch = _batch((n, size), action((n, size)), image)
        if step % 2:  # the flat schedule's per-stage discounts (StageDiscount)
            batch["steps_to_next_obs"] = torch.rand(n, size, 1) + 0.5
        expected = [learner.update(batch[i]) for i, learner in enumerate(singles)]
        losses = stacked.update(batch)
        for key, value in losses.items():
            assert value.shape == (n,), key
            for i in range(n):
                torch.testing.assert_close(value[i], expected[i][key], rtol=1e-4, atol=1e-6)
    for i, single in enumerate(singles):
        out = unstack_learner(stacked, i, make_learner(cfg, specs)).state_dict()
        for key, value in single.state_dict().items():
            torch.testing.assert_close(out[key], value, rtol=1e-4, atol=1e-6, msg=key)
    # the stage value of every seed, on a seed-major batch
    obs = TensorDict(_obs((n * 5,), image), batch_size=[n * 5])
    stacked_v = stacked.value()(obs.clone())["state_value"]
    for i, single in enumerate(singles):
        part = obs[i * 5 : (i + 1) * 5].clone()
        torch.testing.assert_close(
            stacked_v[i * 5 : (i + 1) * 5], single.value()(part)["state_value"], atol=1e-5, rtol=0
        )


@pytest.mark.parametrize("algo", list(CASES))
def test_updating_some_rows_updates_those_seeds_alone(algo, monkeypatch):
    _same_noise_per_seed(monkeypatch)
    # what a stage of many seeds does once some have stopped: the others update as they would
    # on their own, and a stopped seed's parameters get no gradient
    cfg, _, action = CASES[algo]
    specs = _specs(algo)
    n, size, rows = 3, 16, torch.tensor([0, 2])
    singles = [make_learner(cfg, specs) for _ in range(n)]
    stacked = stack_learners(make_learner(cfg, specs, seeds=n), singles)
    batch = _batch((2, size), action((2, size)), algo.endswith("cnn"))
    expected = [singles[int(r)].update(batch[i]) for i, r in enumerate(rows)]
    with update_rows(rows):
        losses = stacked.update(batch)
    for key, value in losses.items():
        if not key.startswith("grad_norm"):
            assert value.shape == (2,), key
            for i in range(2):
                torch.testing.assert_close(value[i], expected[i][key], rtol=1e-4, atol=1e-6)
        else:  # every seed's norm: the stopped one's is zero
            assert value.shape == (n,) and value[1] == 0, key
    for r in rows.tolist():
        out = unstack_learner(stacked, r, make_learner(cfg, specs)).state_dict()
        for key, value in singles[r].state_dict().items():
            torch.testing.assert_close(out[key], value, rtol=1e-4, atol=1e-6, msg=key)


def test_the_value_of_a_stage_of_many_seeds_is_read_from_the_learner_they_trained_in():
    task = two_stage_grid(DQNConfig(num_cells=[8]))
    cfg, specs = task.stage_cfg(1), task.specs(1)
    stacked = make_learner(cfg, specs, seeds=2)
    rows = [unstack_learner(stacked, i, make_learner(cfg, specs)) for i in range(2)]
    for i, row in enumerate(rows):
        row.stacked_row = (stacked, i)
    obs = task.stage_env(1, 4, copies=2).reset()
    read = backward_module.stage_value(task, 1, rows)(obs.clone())["state_value"]
    # in another order the rows are not those of the stacked learner: stacked anew
    swap = torch.arange(8).roll(4)  # the seeds' halves of the batch swapped
    restacked = backward_module.stage_value(task, 1, rows[::-1])(obs[swap].clone())
    assert torch.equal(read, restacked["state_value"][swap])
    assert not torch.equal(read[:4], read[4:])


def test_stacked_networks_refuse_what_cannot_be_stacked():
    own = OmegaConf.create({"algo": "tiny_q", "learner": {"_target_": "my_learner.TinyQLearner"}})
    specs = StageSpecs(["observation"], 3, "action", Categorical(4))
    with pytest.raises(ConfigError, match="tiny_q: cannot train several seeds in one process"):
        make_learner(own, specs, seeds=2)
    with stacked_networks(2), pytest.raises(TypeError, match="LayerNorm"):
        stack_for_seeds(torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.LayerNorm(4)))
    with stacked_networks(2), pytest.raises(TypeError, match="dilation"):
        stack_for_seeds(torch.nn.Conv2d(1, 4, 3, dilation=2))
    with stacked_networks(2):
        net = mlp(4, 2, [8])
        cnn = mlp([(1, 6, 6)], 2, [8])
    assert all(type(m) is not torch.nn.Linear for m in net.modules())
    assert isinstance(net[0], StackedLinear) and net[0].weight.shape == (2, 8, 4)
    convs = [m for m in cnn.modules() if isinstance(m, StackedConv2d)]
    assert convs and not any(type(m) is torch.nn.Conv2d for m in cnn.modules())


def test_a_seed_row_reads_and_restores_one_seed():
    specs = StageSpecs(["observation"], 3, "action", Categorical(4))
    stacked = make_learner(DQNConfig(), specs, seeds=3)
    row = SeedRow(stacked, 1)
    saved = row.state_dict()
    assert all(v.shape == stacked.state_dict()[k].shape[1:] for k, v in saved.items())
    before = {k: v.clone() for k, v in stacked.state_dict().items()}
    moved = {}  # every seed's weights move, targets included (entries alias: once each)
    for key, value in stacked.state_dict(keep_vars=True).items():
        if key in saved:
            moved.setdefault(value.data_ptr(), value)
    with torch.no_grad():
        for value in moved.values():
            value.data.add_(1.0)
    row.load_state_dict(saved)
    after = stacked.state_dict()
    for key, value in saved.items():
        torch.testing.assert_close(after[key][1], value)
        torch.testing.assert_close(after[key][0], before[key][0] + 1.0)


def test_seed_replay_rings_fill_at_each_seeds_pace():
    # the joint schedule's stage buffers: each seed brings its own number of transitions
    generator = torch.Generator().manual_seed(0)
    n, size = 3, 7
    rb = SeedReplayBuffer(size, num_seeds=n)
    held: list[list[int]] = [[] for _ in range(n)]
    value = 0
    for _ in range(40):
        m = int(torch.randint(1, 20, (1,), generator=generator))
        seeds = torch.randint(0, n, (m,), generator=generator)  # in any order
        x = torch.arange(value, value + m)
        value += m
        rb.extend(TensorDict(x=x, next=TensorDict(y=-x, batch_size=[m]), batch_size=[m]), seeds)
        for seed, v in zip(seeds.tolist(), x.tolist(), strict=True):
            held[seed] = [*held[seed], v][-size:]  # each seed's newest `size`
        for i in range(n):
            count = int(rb.counts[i])
            assert sorted(rb.storage["x"][i, :count].tolist()) == sorted(held[i])
            assert torch.equal(rb.storage["next", "y"][i, :count], -rb.storage["x"][i, :count])
        copy = SeedReplayBuffer(size, num_seeds=n)
        copy.load_state_dict(rb.state_dict())
        assert torch.equal(copy.counts, rb.counts) and torch.equal(copy.cursors, rb.cursors)
        if bool((rb.counts > 0).all()):
            drawn = rb.sample(50)["x"]
            assert all(set(drawn[i].tolist()) <= set(held[i]) for i in range(n))
    few = SeedReplayBuffer(4, num_seeds=2)
    few.extend(TensorDict(x=torch.tensor([5]), batch_size=[1]), torch.tensor([1]))
    assert few.counts.tolist() == [0, 1]
    assert few.sample(3, torch.tensor([1]))["x"].tolist() == [[5, 5, 5]]
    with pytest.raises(ValueError, match=r"seeds \[0\] hold no transitions"):
        few.sample(3)


def test_seed_replay_keeps_each_seeds_transitions_apart():
    rb = SeedReplayBuffer(5, num_seeds=2)
    for step in range(4):  # 3 per seed per extend: the ring wraps
        x = torch.tensor([0, 0, 0, 1, 1, 1]) * 1000 + step
        rb.extend(TensorDict(x=x, batch_size=[6]))
    assert len(rb) == 5
    sample = rb.sample(64)["x"]
    assert sample.shape == (2, 64)
    assert bool((sample[0] < 1000).all()) and bool((sample[1] >= 1000).all())
    assert set((sample[0] % 1000).tolist()) <= {1, 2, 3}  # the 5 newest: steps 2, 3 (and 1)
    only = rb.sample(64, torch.tensor([1]))["x"]
    assert only.shape == (1, 64) and bool((only >= 1000).all())


def test_stage_envs_hold_one_copy_of_the_starts_per_seed():
    task = two_stage_grid({"gamma": 0.9}, {"gamma": 0.9, "eval_episodes": 4})
    one = task.stage_eval_env(1).base_env.start_cell
    three = task.stage_eval_env(1, copies=3).base_env.start_cell
    assert three.shape[0] == 3 * one.shape[0]
    assert torch.equal(three, one.repeat(3, 1))
    assert task.stage_env(1, 8, copies=3).batch_size == (24,)
    tiled = tile_starts({"batch_size": (2,), "start_cell": torch.zeros(2, 2)}, 1)
    assert tiled["batch_size"] == (2,)


def test_validate_seeds_names_each_fix(monkeypatch):
    def cfg(seeds, schedule="backward", probe=False):
        return OmegaConf.create(
            {"seeds": seeds, "schedule": {"name": schedule}, "eval": {"probe": probe}}
        )

    assert validate_seeds(cfg([3, 1])) == [3, 1]
    for bad, match in [
        ([], "non-empty list"),
        ([0, -1], "int >= 0"),
        ([0, 0], r"listed twice. Fix: seeds=\[0\]"),
    ]:
        with pytest.raises(ConfigError, match=match):
            validate_seeds(cfg(bad))
    with monkeypatch.context() as patch:  # a schedule that trains its seeds apart
        patch.setattr(JointSchedule, "stacks_seeds", False)
        with pytest.raises(ConfigError, match="schedule=joint seed=0,1"):
            validate_seeds(cfg([0, 1], schedule="joint"))
    with pytest.raises(ConfigError, match="eval.probe=false"):
        validate_seeds(cfg([0, 1], probe=True))


@pytest.mark.e2e
def test_stages_train_seeds_writes_one_ordinary_run_per_seed(tmp_path):
    """The grid world learns on every seed, each seed's directory loads like a single run's,
    the same command with resume=true loads the finished stages, and the sweep summary covers
    the seeds."""
    run_dir = tmp_path / "run"
    two_stages = [o for o in tiny_grid() if not o.startswith("task.stages.")]  # their defaults
    argv = ["stages-train", "seeds=[0,3]", f"hydra.run.dir={run_dir}", *two_stages]
    stale = run_dir / "seed_checkpoints" / "stage_1" / "frames-000000000128"
    stale.mkdir(parents=True)  # a checkpoint no seed's run knows of: a new run drops it
    done = run_cli(argv, tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert not (run_dir / "seed_checkpoints").exists()
    for seed in (0, 3):  # the lines of each seed's stages name it, as its evaluation does
        for k in (0, 1):
            assert f"seed {seed}: stage {k} (s{k}, dqn): " in done.stdout
        assert f"Run directory: {run_dir / f'seed_{seed}'}" in done.stdout
    assert f"  summary.md: {run_dir / 'summary.md'}" in done.stdout
    for seed in (0, 3):
        seed_dir = run_dir / f"seed_{seed}"
        run = load_run(seed_dir)
        assert run.cfg.seed == seed and run.cfg.seeds is None
        assert len(run.learners) == 2
        result = json.loads((seed_dir / "eval.json").read_text())
        assert result["success_rate"] == 1.0, (seed, result)
        assert result["training"]["trained_with_seeds"] == [0, 3]
        assert (seed_dir / "metrics.csv").read_text().count("eval/stage_0/success_rate") >= 1
        overrides = OmegaConf.load(seed_dir / ".hydra" / "overrides.yaml")
        assert f"seed={seed}" in overrides and not any("seeds" in o for o in overrides)
    summary = (run_dir / "summary.md").read_text()
    assert "2 jobs (2 done)" in summary
    again = run_cli([*argv, "resume=true"], tmp_path)
    assert again.returncode == 0, again.stderr[-2000:]
    assert (again.stdout + again.stderr).count("finished earlier, loaded") == 4
    assert "seed 3: stage 0 (s0): finished earlier, loaded" in again.stdout
    # a damaged stage file: its fix, followed as printed, retrains that stage and those trained
    # after it for every seed, so that no seed keeps a stage trained against another stage 1
    damaged = run_dir / "seed_3" / "stage_1.pt"
    damaged.write_bytes(damaged.read_bytes()[:100])
    refused = run_cli([*argv, "resume=true"], tmp_path)
    assert refused.returncode == 2, refused.stderr[-2000:]
    fix = f"delete it and rerun the same stages-train command with hydra.run.dir={run_dir} "
    assert f"{damaged} is damaged" in refused.stderr and fix in refused.stderr
    damaged.unlink()
    repaired = run_cli([*argv, "resume=true"], tmp_path)
    assert repaired.returncode == 0, repaired.stderr[-2000:]
    assert "stage 1 is finished for some seeds but not for seeds [3]" in repaired.stdout
    for seed in (0, 3):
        assert all(f"seed {seed}: stage {k} (s{k}, dqn): " in repaired.stdout for k in (0, 1))
    # a learner that does not stack (the user's own): refused before anything is trained or
    # written
    other = tmp_path / "other"
    own = ["stages-train", "seeds=[0,1]", f"hydra.run.dir={other}", *two_stages]
    own.append("+task.stages.s0.learner._target_=my_learner.TinyQLearner")
    refused = run_cli(own, tmp_path, PYTHONPATH=str(Path(__file__).parent))
    assert refused.returncode == 2, refused.stderr[-2000:]
    assert "task.stages.s0: algo=tiny_q: cannot train several seeds" in refused.stderr
    assert not list(other.glob("seed_*/stage_*.pt"))


def _tiny_task(frames: int = 2048) -> StagedTask:
    # a low bar: seeds 3 and 5 meet it at different times (stage 0: 384 and 1536 frames)
    stage = DQNConfig(
        frames=frames,
        frames_per_batch=128,
        num_envs=16,
        init_random_frames=128,
        batch_size=32,
        updates_per_batch=2,
        eval_every=128,
        eval_episodes=8,
        eval_max_steps=64,  # an untrained greedy policy ends its episodes here, not at 200
        success_threshold=0.5,
        min_frames=0,
    )
    return two_stage_grid(stage)


def test_an_interrupted_stage_of_many_seeds_resumes_bitwise_from_its_checkpoint(
    tmp_path, monkeypatch
):
    # the stop a signal asks for (SIGTERM) writes a checkpoint of every seed at once; the
    # next launch goes on from it (a seed that had stopped stays stopped), each seed's log
    # rewound to it, and ends where an uninterrupted launch ends, bit for bit
    seeds = [0, 3, 5]

    def launch(root):
        logs = [MetricsLog(RunLogger(root / f"seed_{s}.csv")) for s in seeds]

        def checkpoints(scope):
            return StageCheckpoints(root / f"stage_{scope}", every=256, keep=2)

        return train_backward(_tiny_task(), seeds, logs=logs, checkpoints=checkpoints)

    reference = launch(tmp_path / "reference")
    stages = [[(r.frames, r.early_stopped) for r in run.results] for run in reference]
    assert stages[1][0] == (384, True) and stages[0][0] == (2048, False)  # what it covers
    interrupted = tmp_path / "interrupted"
    periodic = interrupted / "stage_0" / "frames-000000000512"

    def stop_after_the_checkpoint_at_512():  # stage 0, seed 3 stopped (at 384)
        return signal.SIGTERM if periodic.exists() else None

    monkeypatch.setattr(loop_module, "requested", stop_after_the_checkpoint_at_512)
    with pytest.raises(Interrupted, match="stage 0"):
        launch(interrupted)
    monkeypatch.undo()
    # named by each seed's frames: periodic at 512, the signal's at 640 (one batch later)
    names = sorted(p.name for p in (interrupted / "stage_0").iterdir())
    assert names == ["frames-000000000512", "frames-000000000640"]
    resumed = launch(interrupted)
    for ref, res in zip(reference, resumed, strict=True):
        for k in (0, 1):
            assert ref.results[k].frames == res.results[k].frames
            assert ref.results[k].updates == res.results[k].updates
            assert ref.results[k].early_stopped == res.results[k].early_stopped
            a, b = ref.learners[k].state_dict(), res.learners[k].state_dict()
            assert all(torch.equal(a[key], b[key]) for key in a), k
    for s in seeds:
        logged = (interrupted / f"seed_{s}.csv").read_bytes()
        assert logged == (tmp_path / "reference" / f"seed_{s}.csv").read_bytes()
    assert not (interrupted / "stage_0").exists()  # dropped once the stage is kept


def _logged(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name.startswith("torchrl_stages")]


def test_away_from_a_terminal_each_seed_s_evaluations_log_lines_naming_it(monkeypatch, caplog):
    monkeypatch.setattr(sys, "stderr", io.StringIO())  # not a terminal: lines, not a bar
    caplog.set_level(logging.INFO, logger="torchrl_stages")
    train_backward(_tiny_task(frames=256), [3, 5], progress=True)
    shown = [line.split(", success")[0] for line in _logged(caplog)]
    assert shown == [
        f"seed {seed}: stage {k} ({name}): {frames} of 256 frames"
        for k, name in ((1, "b"), (0, "a"))
        for frames in (128, 256)
        for seed in (3, 5)
    ]


@pytest.mark.slow
def test_the_joint_phases_of_stacked_seeds_log_the_seeds_still_training(monkeypatch, caplog):
    # seed 2 stops the phase from stage 1 at 768 frames (see the test of its resume above):
    # from then on only seed 1's evaluations are logged, until the next phase
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    caplog.set_level(logging.INFO, logger="torchrl_stages")
    JointSchedule().train(_tiny_task(frames=1024), [1, 2], progress=True)
    phase_1 = [line for line in _logged(caplog) if "the joint phase from stage 1 (b)" in line]
    seeds = [line.split(":")[0] for line in phase_1]
    assert seeds == ["seed 1", "seed 2"] * 6 + ["seed 1"] * 2
    assert phase_1[-1].startswith("seed 1: the joint phase from stage 1 (b): 1024 of 1024 frames")
    phase_0 = [line for line in _logged(caplog) if "the joint phase from stage 0 (a)" in line]
    assert [line.split(":")[0] for line in phase_0] == ["seed 1", "seed 2"] * 8


def _two_seeds_in_one_process(compose_cfg, tmp_path, *overrides: str) -> list[dict]:
    """An ``Experiment`` of seeds 0 and 1 in ``tmp_path / "run"``, smoke budget: each seed's
    ``eval.json``."""
    quiet = ["experiment=smoke", "seeds=[0,1]", "eval.plots=false", "progress=false"]
    return Experiment(compose_cfg(*overrides, *quiet), tmp_path / "run").run()


def test_td3_seeds_train_in_one_process(compose_cfg, tmp_path):
    # twin critics and a delayed actor loss (logged on every other update) through the whole run
    results = _two_seeds_in_one_process(
        compose_cfg,
        tmp_path,
        "task=manipulator",
        "algo@task.stages.coarse=td3",
        "algo@task.stages.fine=td3",
    )
    assert len(results) == 2
    for seed in (0, 1):
        logged = (tmp_path / "run" / f"seed_{seed}" / "metrics.csv").read_text()
        assert "train/stage_0/loss_actor" in logged and "train/stage_1/loss_qvalue" in logged
        assert load_run(tmp_path / "run" / f"seed_{seed}").cfg.task.stages.fine.algo == "td3"


@pytest.mark.parametrize(
    ("task", "algo", "stages"),
    [("manipulator", "sac", ("coarse", "fine")), ("gridworld", "discrete_sac", ("s0", "s4"))],
)
def test_sac_seeds_train_in_one_process_each_with_its_own_entropy_coefficient(
    compose_cfg, tmp_path, task, algo, stages
):
    picks = [f"algo@task.stages.{stage}={algo}" for stage in stages]
    results = _two_seeds_in_one_process(compose_cfg, tmp_path, f"task={task}", *picks)
    assert len(results) == 2
    for seed in (0, 1):
        run = load_run(tmp_path / "run" / f"seed_{seed}")  # an ordinary run: one alpha
        stage = run.cfg.task.stages[stages[-1]]
        assert stage.algo == algo
        log_alpha = run.learners[-1].loss.log_alpha
        assert log_alpha.shape == () and bool(torch.isfinite(log_alpha))
        # tuned: moved from its start (that each seed's moves on its own batches is
        # test_a_stacked_learner_updates_each_seed_as_its_own_learner_would's)
        assert log_alpha.item() != pytest.approx(math.log(stage.alpha_init), abs=1e-6)
        logged = (tmp_path / "run" / f"seed_{seed}" / "metrics.csv").read_text()
        assert f"train/stage_{len(run.learners) - 1}/alpha" in logged


class _Captured(Exception):
    pass


def test_each_flat_seed_starts_from_the_weights_of_its_own_flat_run(monkeypatch):
    task = two_stage_grid(DQNConfig(gamma=0.9, frames=256), DQNConfig(gamma=0.5, frames=256))
    seen = {}

    def capture(kind):
        def trainer(stage, learner, env, eval_env, cfg, **kwargs):
            seen[kind] = (learner, env, eval_env, kwargs)
            raise _Captured

        return trainer

    monkeypatch.setattr(backward_module, "StageTrainer", capture("trainer"))
    with pytest.raises(_Captured):
        flat_module.train_flat(task, [4, 1])
    stacked, env, eval_env, kwargs = seen["trainer"]
    assert kwargs["gammas"] == [0.9, 0.5] and kwargs["extra_keys"] == ["steps_to_next_obs"]
    single_env = task.task_env(int(task.stage_cfg(0).num_envs), start_stage=None, train=True)
    assert env.batch_size[0] == 2 * single_env.batch_size[0]
    assert eval_env.batch_size[0] == 2 * task.task_env(None).batch_size[0]
    for i, seed in enumerate([4, 1]):
        with pytest.raises(_Captured):
            flat_module.train_flat(task, [seed])
        single = seen["trainer"][0].state_dict()
        row = unstack_learner(
            stacked, i, make_learner(flat_module.flat_config(task), task.specs(0))
        )
        assert all(torch.equal(row.state_dict()[k], v) for k, v in single.items()), seed


def test_flat_seeds_train_in_one_process(compose_cfg, tmp_path):
    results = _two_seeds_in_one_process(compose_cfg, tmp_path, "schedule=flat")
    assert len(results) == 2
    for seed in (0, 1):
        seed_dir = tmp_path / "run" / f"seed_{seed}"
        run = load_run(seed_dir)
        assert run.cfg.schedule.name == "flat" and run.cfg.seed == seed
        assert len({id(learner) for learner in run.learners}) == 1  # one learner acts everywhere
        result = json.loads((seed_dir / "eval.json").read_text())
        assert len(result["training"]["stages"]) == 1
        assert "eval/stage_0/success_rate" in (seed_dir / "metrics.csv").read_text()


def _stopped_then_resumed(monkeypatch, launch, periodic, where: str):
    """``launch(root)`` stopped by SIGTERM once the checkpoint ``periodic`` (in ``root``) is
    written, then launched again: what the second launch returns."""
    root = periodic.parent.parent
    monkeypatch.setattr(
        loop_module, "requested", lambda: signal.SIGTERM if periodic.exists() else None
    )
    with pytest.raises(Interrupted, match=where):
        launch(root)
    monkeypatch.undo()
    assert periodic.exists()  # what the next launch goes on from
    return launch(root)


def test_an_interrupted_flat_run_of_many_seeds_resumes_bitwise_from_its_checkpoint(
    tmp_path, monkeypatch
):
    seeds = [0, 3]
    stage = DQNConfig(
        gamma=0.9,
        frames=512,  # the flat learner's budget: the stages' sum
        frames_per_batch=128,
        num_envs=16,
        init_random_frames=128,
        batch_size=32,
        updates_per_batch=2,
        eval_every=256,
        eval_episodes=8,
        success_threshold=1.1,  # never met: both seeds train the whole budget
        min_frames=0,
    )
    task = two_stage_grid(stage, dataclasses.replace(stage, gamma=0.5))

    def launch(root):
        logs = [MetricsLog(RunLogger(root / f"seed_{s}.csv")) for s in seeds]

        def checkpoints(scope):
            return StageCheckpoints(root / f"stage_{scope}", every=256, keep=2)

        return flat_module.train_flat(task, seeds, logs=logs, checkpoints=checkpoints)

    reference = launch(tmp_path / "reference")
    interrupted = tmp_path / "interrupted"
    periodic = interrupted / "stage_0" / "frames-000000000512"
    resumed = _stopped_then_resumed(monkeypatch, launch, periodic, "stage 0")
    assert not (interrupted / "stage_0").exists()  # dropped once the learner is kept
    for ref, res in zip(reference, resumed, strict=True):
        assert ref.learners[0] is ref.learners[1] and res.learners[0] is res.learners[1]
        assert ref.results[0].frames == res.results[0].frames == 1024
        a, b = ref.learners[0].state_dict(), res.learners[0].state_dict()
        assert all(torch.equal(a[key], b[key]) for key in a)
    for s in seeds:
        logged = (interrupted / f"seed_{s}.csv").read_bytes()
        assert logged == (tmp_path / "reference" / f"seed_{s}.csv").read_bytes()


def test_image_inputs_train_in_one_process(compose_cfg, tmp_path):
    # cargo: the slider's TD3 with one CNN for its actor and critics, then the propelled
    # robot's DQN over a CNN, each seed's convolutions one group of a grouped convolution
    results = _two_seeds_in_one_process(compose_cfg, tmp_path, "task=cargo")
    assert len(results) == 2
    for seed in (0, 1):
        run = load_run(tmp_path / "run" / f"seed_{seed}")
        assert any(isinstance(m, torch.nn.Conv2d) for m in run.learners[0].modules())


def test_each_joint_seed_starts_from_the_weights_of_its_own_joint_run():
    task = _tiny_task()
    trainer = JointTrainer(task, [4, 1])
    assert trainer.buffers[0].num_seeds == 2
    cfg = task.stage_cfg(1)
    env, eval_env = trainer._phase_envs(1, 1, cfg)
    assert env.batch_size == (2 * int(cfg.num_envs),)  # one copy of each batch per seed
    starts = JointTrainer(task)._phase_envs(1, 1, cfg)[1].batch_size[0]  # every stage-1 start
    assert eval_env.batch_size[0] == 2 * starts
    for i, seed in enumerate([4, 1]):
        single = JointTrainer(task, [seed]).learners
        for m, learner in enumerate(single):
            row = unstack_learner(
                trainer.learners[m], i, make_learner(task.stage_cfg(m), task.specs(m))
            )
            own = learner.state_dict()
            assert all(torch.equal(row.state_dict()[k], v) for k, v in own.items()), (seed, m)


def test_joint_seeds_train_in_one_process(compose_cfg, tmp_path):
    results = _two_seeds_in_one_process(compose_cfg, tmp_path, "schedule=joint")
    assert len(results) == 2
    for seed in (0, 1):
        seed_dir = tmp_path / "run" / f"seed_{seed}"
        run = load_run(seed_dir)
        assert run.cfg.schedule.name == "joint" and run.cfg.seed == seed
        assert len(run.learners) == run.task.num_stages
        training = json.loads((seed_dir / "eval.json").read_text())["training"]
        phases = [phase["start_stage"] for phase in training["phases"]]
        assert phases == list(reversed(range(run.task.num_stages)))
        assert all(stage["updates"] > 0 for stage in training["stages"])
        logged = (seed_dir / "metrics.csv").read_text()
        assert "eval/joint_0/success_rate" in logged and "train/stage_0/loss" in logged
        steps = [int(line.split(",")[1]) for line in logged.splitlines()[1:]]
        assert steps == sorted(steps)  # each seed's frames, counted on across the phases


def test_an_interrupted_joint_run_of_many_seeds_resumes_bitwise_from_its_checkpoint(
    tmp_path, monkeypatch
):
    # seed 2 stops in the phase from stage 1 (at 768 frames), seed 1 trains it on: the signal
    # comes after the stop, inside the first phase; the second phase follows the resume
    seeds = [1, 2]
    task = _tiny_task(frames=1024)

    def launch(root):
        logs = [MetricsLog(RunLogger(root / f"seed_{s}.csv")) for s in seeds]

        def checkpoints(scope):
            return StageCheckpoints(root / scope, every=256, keep=2)

        return JointSchedule().train(task, seeds, logs=logs, checkpoints=checkpoints)

    reference = launch(tmp_path / "reference")
    stops = [[(p["frames"], p["early_stopped"]) for p in run.extra["phases"]] for run in reference]
    assert stops[1][0] == (768, True) and stops[0][0] == (1024, False)  # what it covers
    interrupted = tmp_path / "interrupted"
    periodic = interrupted / "joint" / "frames-000000000768"
    resumed = _stopped_then_resumed(monkeypatch, launch, periodic, "joint phase from stage 1")
    assert not (interrupted / "joint").exists()  # dropped once the stages are kept
    for ref, res in zip(reference, resumed, strict=True):
        assert ref.extra["phases"] == res.extra["phases"]
        for k in (0, 1):
            assert ref.results[k].frames == res.results[k].frames
            assert ref.results[k].updates == res.results[k].updates
            a, b = ref.learners[k].state_dict(), res.learners[k].state_dict()
            assert all(torch.equal(a[key], b[key]) for key in a), k
    for s in seeds:
        logged = (interrupted / f"seed_{s}.csv").read_bytes()
        assert logged == (tmp_path / "reference" / f"seed_{s}.csv").read_bytes()


def test_a_stopped_seeds_adam_moments_are_put_back():
    # the joint schedule: a seed that stops in a phase goes on in the next one; meanwhile its
    # rows get no gradient, but Adam decays their moments at every step of the others
    cfg, _, action = CASES["dqn"]
    specs = _specs("dqn")
    stacked = make_learner(cfg, specs, seeds=2)
    for _ in range(3):
        stacked.update(_batch((2, 8), action((2, 8))))
    row_0, row_1 = SeedRow([stacked], 0), SeedRow([stacked], 1)
    kept = row_1.moments()
    assert kept and all("exp_avg" in key for key in kept)
    with update_rows(torch.tensor([0])):
        for _ in range(3):
            stacked.update(_batch((1, 8), action((1, 8))))
    decayed = row_1.moments()
    assert any(not torch.equal(decayed[k], v) for k, v in kept.items())
    seed_0 = row_0.moments()
    row_1.moments(load=kept)
    assert all(torch.equal(row_1.moments()[k], v) for k, v in kept.items())
    assert all(torch.equal(row_0.moments()[k], v) for k, v in seed_0.items())
