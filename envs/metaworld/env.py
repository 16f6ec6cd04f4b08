"""Meta-World's manipulation tasks (v3, MuJoCo) as two-stage tasks: grasp the object, then bring
it where the task wants it. The gymnasium wrapper :class:`StagedMetaWorld` and the batched
:class:`MetaWorldEnv`; ``docs/tasks/metaworld.md`` says what each choice is for."""

from __future__ import annotations

import functools
import warnings
from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
import torch

from torchrl_stages.gym_env import GymStageEnv

from .._common import check_start_stage

__all__ = ["STAGES", "MetaWorldEnv", "StagedMetaWorld", "import_metaworld", "make_task"]

#: the stages: until Meta-World's ``grasp_success`` (the object held off the table), then until
#: its ``success``
STAGES = ("grasp", "place")
#: each stage's potential, Meta-World's own shaping term of that stage (in [0, 1])
POTENTIALS = ("grasp_reward", "in_place_reward")
PREFIX_STEPS = 300  # scripted steps a stage-1 start may take to grasp before it is drawn again
ATTEMPTS = 10  # scripted attempts per stage-1 start


#: the gymnasium id of :func:`make_task`, registered by :func:`import_metaworld`
ENV_ID = "torchrl_stages/MetaWorld-MT1"
EPISODE_STEPS = 500  # the benchmark's episode length (Meta-World's max_path_length)


def import_metaworld() -> Any:
    """The ``metaworld`` package, with :data:`ENV_ID` registered, or an error with the fix."""
    try:
        import metaworld
    except ImportError as err:
        raise ImportError(
            "task=metaworld needs Meta-World. Fix: pip install 'torchrl-stages[metaworld]' "
            f"(or pip install metaworld) ({err})"
        ) from None
    if ENV_ID not in gymnasium.registry:
        entry = f"{__name__}:make_task"
        gymnasium.register(ENV_ID, entry_point=entry, max_episode_steps=EPISODE_STEPS)
    return metaworld


def scripted_policy(env_name: str) -> Any:
    """The task's scripted policy (``metaworld.policies``); a name without one is refused."""
    from metaworld.policies import ENV_POLICY_MAP

    if env_name not in ENV_POLICY_MAP:
        raise ValueError(
            f"env_name={env_name!r} is not a Meta-World v3 task. Fix: set task.env.env_name "
            f"to one of {', '.join(sorted(ENV_POLICY_MAP))}"
        )
    return ENV_POLICY_MAP[env_name]()


@functools.cache
def _benchmark(env_name: str, seed: int) -> Any:
    import metaworld

    return metaworld.MT1(env_name, seed=seed)  # 0.6 s: once per process


def make_task(env_name: str, seed: int = 0) -> gymnasium.Env:
    """Meta-World's MT1 env of ``env_name``, as ``gymnasium.make("Meta-World/MT1", ...)`` builds
    it: one of the benchmark's 50 placements (of ``seed``) drawn at each reset."""
    from metaworld.wrappers import RandomTaskSelectWrapper

    benchmark = _benchmark(env_name, int(seed))
    env = benchmark.train_classes[env_name]()
    env.seed(int(seed))
    return RandomTaskSelectWrapper(env, list(benchmark.train_tasks))


class StagedMetaWorld(gymnasium.Wrapper):
    """A Meta-World task (its MT1 env, :func:`make_task`) in two stages, ``grasp`` then ``place``.

    The stage moves on once Meta-World's ``info["grasp_success"]`` holds and never goes back;
    the episode terminates on ``info["success"]``, the benchmark's own flag. The reward is 1 on
    success plus a potential-based shaping term (Ng et al., 1999). Stage k's potential is
    ``Phi_k = shaping * info[POTENTIALS[k]]``, Meta-World's own term of that stage, of the state:
    a step inside stage k gains ``gamma Phi_k(s') - Phi_k(s)``, the step that leaves it
    ``gamma Phi_{k+1}(s') - Phi_k(s)`` and the step that succeeds ``-Phi_k(s)``. Over stage k the
    terms add up to ``-Phi_k(s_0)`` plus what the next stage's value gives back, so every
    stage's best policy is that of the sparse reward, and so is the flat learner's over the
    whole task. ``gamma`` must be the stages' discount.

    ``start_stage=1`` starts inside ``place``: from a reset, the task's scripted policy
    (``metaworld.policies``), its actions with Gaussian noise of scale ``noise``, steps until it
    grasps, then up to ``carry`` more steps while it holds the object (a drawn number); the
    episode's clock then starts at 0. The observation is ``{"observation": float32 [39],
    "stage": int64 [1]}``.

    Examples:
        >>> env = StagedMetaWorld(make_task("pick-place-v3"), "pick-place-v3", start_stage=1)
        >>> obs, _ = env.reset(seed=0)
        >>> int(obs["stage"][0]), obs["observation"].shape, env.unwrapped.curr_path_length
        (1, (39,), 0)
    """

    def __init__(
        self,
        env: gymnasium.Env,
        env_name: str,
        start_stage: int | None = None,
        *,
        gamma: float = 0.99,
        shaping: float = 1.0,
        noise: float = 0.1,
        carry: int = 10,
    ) -> None:
        super().__init__(env)
        self.scripted = scripted_policy(env_name)
        self.stage_names, self.num_stages = list(STAGES), len(STAGES)
        self.start_stage = check_start_stage(start_stage, self.num_stages)
        self.gamma, self.shaping, self.noise, self.carry = gamma, shaping, noise, int(carry)
        size = env.observation_space.shape[0]
        self.observation_space = gymnasium.spaces.Dict(
            observation=gymnasium.spaces.Box(-np.inf, np.inf, (size,), np.float32),
            stage=gymnasium.spaces.Box(0, self.num_stages - 1, (1,), np.int64),
        )
        self.stage, self.potential = 0, 0.0

    def _obs(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        return {
            "observation": np.asarray(obs, np.float32),
            "stage": np.array([self.stage], np.int64),
        }

    def _potential(self, obs: np.ndarray) -> float:
        """``Phi`` of the current stage at ``obs``: Meta-World's term, evaluated with a no-op
        action (its grasp term counts the gripper's effort, which is no part of the state)."""
        if not self.shaping:
            return 0.0
        _, info = self.env.unwrapped.evaluate_state(obs, np.zeros(4, np.float32))
        return self.shaping * float(info[POTENTIALS[self.stage]])

    def _grasped(self, obs: np.ndarray) -> tuple[np.ndarray, dict[str, Any]] | None:
        """The scripted policy, noised, until it grasps, then ``carry`` steps at most while it
        holds; ``None`` where it did not grasp (or already succeeded)."""
        extra, grasped, info = int(self.np_random.integers(self.carry + 1)), False, {}
        for _ in range(PREFIX_STEPS):
            with warnings.catch_warnings():  # its gains warn that the env clips the actions
                warnings.simplefilter("ignore", UserWarning)
                action = self.scripted.get_action(obs)
            action = action + self.noise * self.np_random.standard_normal(action.shape)
            obs, _, _, truncated, info = self.env.step(np.clip(action, -1.0, 1.0))
            if info["success"] or truncated:
                return None
            if info["grasp_success"]:
                grasped = True
                if extra == 0:
                    return obs, info
                extra -= 1
            elif grasped:  # dropped while carried: draw again
                return None
        return None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:  # Meta-World's reset ignores its seed: the generator MT1 draws from
            self.env.unwrapped.seed(int(seed))
        obs, info = self.env.reset(options=options)
        self.stage = 0
        if self.start_stage == 1:
            for _ in range(ATTEMPTS):
                grasped = self._grasped(obs)
                if grasped is not None:
                    obs, info = grasped
                    break
                obs, info = self.env.reset()
            else:
                raise RuntimeError(
                    f"the scripted policy did not grasp in {ATTEMPTS} attempts. Fix: lower "
                    "task.env.noise"
                )
            _restart_clock(self.env)
            self.stage = 1
        self.potential = self._potential(obs)
        return self._obs(obs), info

    def step(self, action):
        obs, _, _, truncated, info = self.env.step(action)
        before, success = self.potential, bool(info["success"])
        if not success and self.stage == 0 and info["grasp_success"]:
            self.stage = 1
        self.potential = 0.0 if success else self._potential(obs)
        reward = float(success) + self.gamma * self.potential - before
        return self._obs(obs), reward, success, bool(truncated), info


def _restart_clock(env: gymnasium.Env) -> None:
    """Sets the episode's step counters (Meta-World's own, every ``TimeLimit``'s) to 0."""
    while isinstance(env, gymnasium.Wrapper):
        if isinstance(env, gymnasium.wrappers.TimeLimit):
            env._elapsed_steps = 0
        env = env.env
    env.unwrapped.curr_path_length = 0


class MetaWorldEnv(GymStageEnv):
    """A Meta-World v3 task (``env_name``, e.g. ``pick-place-v3``) as a batched two-stage TorchRL
    env: ``batch_size[0]`` copies of :class:`StagedMetaWorld` (its keys) in a gymnasium vector
    env. Each copy is the task's MT1 env with the benchmark's ``seed`` (its 50 object and goal
    placements, one drawn per episode) and episodes of ``max_episode_steps`` (``None``: the
    benchmark's 500).

    Examples:
        >>> env = MetaWorldEnv("pick-place-v3", batch_size=(2,), start_stage=1)
        >>> td = env.reset()
        >>> td["stage"].squeeze(-1).tolist(), td["observation"].shape, env.max_steps
        ([1, 1], torch.Size([2, 39]), 500)
        >>> env.close()
    """

    def __init__(
        self,
        env_name: str,
        *,
        seed: int = 0,
        max_episode_steps: int | None = None,
        vectorize: str = "sync",
        batch_size: Sequence[int],
        device: str | torch.device = "cpu",
        start_stage: int | None = None,
        gamma: float = 0.99,
        shaping: float = 1.0,
        noise: float = 0.1,
        carry: int = 10,
        **kwargs: Any,
    ) -> None:
        import_metaworld()
        scripted_policy(env_name)  # refuses an unknown name before any copy is built
        wrapper = functools.partial(
            StagedMetaWorld,
            env_name=env_name,
            start_stage=start_stage,
            gamma=gamma,
            shaping=shaping,
            noise=noise,
            carry=carry,
        )
        limit = {} if max_episode_steps is None else {"max_episode_steps": int(max_episode_steps)}
        if not 0 < limit.get("max_episode_steps", 1) <= EPISODE_STEPS:
            raise ValueError(
                f"max_episode_steps={max_episode_steps}: Meta-World's episodes are at most "
                f"{EPISODE_STEPS} steps. Fix: set task.env.max_episode_steps within 1..500"
            )
        super().__init__(
            ENV_ID,
            stage_fn=None,  # the wrapper writes "stage"
            num_stages=len(STAGES),
            vectorize=vectorize,
            wrappers=[wrapper],
            batch_size=batch_size,
            device=device,
            env_name=env_name,
            seed=int(seed),
            disable_env_checker=True,
            **limit,
            **kwargs,
        )
        self.start_stage, self.env_name = start_stage, env_name
