"""One ManiSkill3 task as a chunk env (see ``stepnft.envs.base`` for the contract).

The scene is ManiSkill's own (``gym.make(task, num_envs=1, sim_backend="cpu")``: PhysX on the
CPU, one scene per chunk env, so stepnft's vector envs and worker processes parallelise it as
they do MuJoCo). ManiSkill's GPU-parallel physics (``sim_backend="gpu"``, thousands of scenes in
one batched env) has a vector env of its own: ``stepnft.envs.maniskill.gpu``.

Observations:
    ``state``  float32 [64]: ManiSkill's ``obs_mode="state"`` vector (the arm's joint positions
               and velocities, the TCP pose, the objects' poses and goal: privileged state),
               zero-padded to ``STATE_DIM`` so that tasks of different sizes share one policy
    ``image``  uint8 [V, 3, S, S] with ``cameras`` (``base_camera`` on every task,
               ``hand_camera`` on the tasks whose robot carries one), S = ``image_size``,
               rendered once per ``step`` call (after the chunk) and at reset
Actions: float32 [n_exec, 7] in [-1, 1], controller ``pd_ee_delta_pose``: end-effector
translation (3, up to 10 cm per step) and rotation (3, axis-angle, up to 0.1 rad) deltas, gripper
(+1 open, -1 closed), 20 env steps per second. An end-effector controller rather than ManiSkill's
RL default ``pd_joint_delta_pos``: the same kind of action as MetaWorld's and LIBERO's, and one a
scripted expert can write from object positions. Reward: ManiSkill's ``normalized_dense`` reward
(in [0, 1] per step); success: its ``info["success"]`` after each env step.

Initial states. ``reset(seed=s)`` resets ManiSkill with seed ``s`` (seeds of 2**32 and above,
stepnft's demonstration seeds, are folded into [2**31, 2**32): ManiSkill takes 32-bit seeds), so
the initial state depends only on (task, s). ManiSkill's unseeded reset would draw from torch's
global RNG; here an unseeded reset draws a seed from the env's own stream instead.

SAPIEN needs a Vulkan device even when nothing is rendered (its materials live on one); without
one, construction raises a ValueError saying what to install.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import seeding

from stepnft.envs.base import ChunkEpisode, checked_chunk
from stepnft.envs.maniskill.tasks import STATE_DIM, TASKS
from stepnft.envs.perturbations import Perturbations

ACTION_DIM = 7
CONTROL_HZ = 20
"""ManiSkill's tabletop tasks: 100 Hz physics, 20 Hz control."""
CONTROL_MODE = "pd_ee_delta_pose"
MAX_EPISODE_STEPS = 500
"""stepnft's cap (ManiSkill has none of its own; its tasks end after 50-250 steps by default)."""
SEED_LIMIT = 2**32
"""ManiSkill seeds numpy's RandomState, which takes seeds below 2**32."""
VULKAN_HINT = ("on Debian 12 run `bash scripts/bootstrap.sh --maniskill` as root (Mesa's lavapipe 25 from "
               "bookworm-backports; Debian's own Mesa 22 is too old), or install your GPU's Vulkan driver; "
               "docs/maniskill.md")


def maniskill_seed(seed: int) -> int:
    """The seed ManiSkill gets for ``reset(seed=seed)``: ``seed`` below 2**32, larger seeds folded
    into [2**31, 2**32) (stepnft's demonstration seeds 2**32 + k land on 2**31 + k, apart from
    the training and evaluation seeds, which stay below 2**31)."""
    return seed if seed < SEED_LIMIT else SEED_LIMIT // 2 + (seed - SEED_LIMIT) % (SEED_LIMIT // 2)


def make_maniskill_env(task: str, **kwargs) -> gym.Env:
    """``gym.make`` of a ManiSkill task; a machine without a usable Vulkan device is a one-line
    ValueError saying what to install."""
    import mani_skill.envs  # noqa: F401  (registers the tasks)

    try:
        return gym.make(task, **kwargs)
    except RuntimeError as err:
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        # SAPIEN's messages when there is no Vulkan driver ("vk::createInstanceUnique:
        # ErrorIncompatibleDriver"), no device ("failed to find a rendering device") or one
        # lacking a feature SAPIEN needs (Mesa 22's lavapipe).
        if any(word in first.lower() for word in ("vk", "vulkan", "device", "feature")):
            raise ValueError(f"ManiSkill needs a Vulkan device, even without cameras, and found none usable "
                             f"({first}): {VULKAN_HINT}") from err
        raise


class ManiSkillChunkEnv(ChunkEpisode, gym.Env):
    """One ManiSkill3 task whose action is a chunk of ``n_exec`` actions, run in order.

    Observation: {"state": float32 [64], with ``cameras`` "image": uint8 [V, 3, image_size,
    image_size]}. Action: float32 [n_exec, 7] in [-1, 1]; rows are clipped to [-1, 1] before
    they reach the simulator. See the module doc for both.

    ``step`` stops early when the task succeeds (if ``terminate_on_success``) or the episode
    reaches ``max_episode_steps`` env steps, and returns the summed reward and info
    (``success``, ``steps``, ``episode_steps``). Stepping an ended episode is a no-op (see
    ``stepnft.envs.base``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}

    def __init__(
        self,
        task: str,
        n_exec: int = 4,
        max_episode_steps: int = 200,
        terminate_on_success: bool = True,
        seed: int = 0,
        render_size: tuple[int, int] | None = None,
        cameras: Sequence[str] = (),
        image_size: int = 64,
        state_obs: str = "full",
        perturbations: Perturbations | Sequence[str] | None = None,
    ):
        if task not in TASKS:
            raise ValueError(f"unknown ManiSkill task {task!r}; valid names: {', '.join(TASKS)}")
        if n_exec < 1:
            raise ValueError(f"n_exec must be >= 1, got {n_exec}")
        if not 1 <= max_episode_steps <= MAX_EPISODE_STEPS:
            raise ValueError(f"max_episode_steps must be in [1, {MAX_EPISODE_STEPS}], got {max_episode_steps}")
        if state_obs != "full":
            raise ValueError(f"ManiSkill offers only state_obs 'full', got {state_obs!r}")
        if perturbations:
            raise ValueError("ManiSkill has no perturbation suites here: drop --env.randomize")
        if cameras and not 8 <= image_size <= 480:
            raise ValueError(f"image_size must be in [8, 480], got {image_size}")
        self.task = task
        self.instruction = TASKS[task].instruction
        self.n_exec = n_exec
        self.max_episode_steps = max_episode_steps
        self.terminate_on_success = terminate_on_success
        self.render_mode = "rgb_array" if render_size else None
        self.cameras = list(cameras)

        spaces = {"state": gym.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32)}
        if cameras:
            spaces["image"] = gym.spaces.Box(0, 255, (len(cameras), 3, image_size, image_size), np.uint8)
        self.observation_space = gym.spaces.Dict(spaces)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n_exec, ACTION_DIM), np.float32)

        renders = bool(cameras or render_size)
        kwargs: dict[str, Any] = dict(
            obs_mode="state", control_mode=CONTROL_MODE, reward_mode="normalized_dense", sim_backend="cpu",
            num_envs=1,
            # "none" skips the render system of state-only envs (SAPIEN still wants a Vulkan
            # device for their materials); "cpu" names the device outright instead of letting
            # ManiSkill look for CUDA first and warn.
            render_backend="cpu" if renders else "none",
            # This env counts the episode's steps itself: ManiSkill's own time limit stays out of the way.
            max_episode_steps=10**9,
        )
        if cameras:
            kwargs["sensor_configs"] = dict(width=image_size, height=image_size)
        if render_size:
            kwargs |= dict(render_mode="rgb_array",
                           human_render_camera_configs=dict(height=render_size[0], width=render_size[1]))
        self._env = make_maniskill_env(task, **kwargs)
        self._base = self._env.unwrapped
        unknown = [c for c in self.cameras if c not in self._base._sensors]
        if unknown:
            self._env.close()
            raise ValueError(f"unknown ManiSkill camera {unknown[0]!r} for {task}; its cameras: "
                             f"{', '.join(self._base._sensors)}")
        self.np_random, _ = seeding.np_random(seed)

        self._state: np.ndarray | None = None
        self._image: np.ndarray | None = None
        self.render_seconds = 0.0
        """Time spent rendering observation images since construction (benchmarks read it)."""

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Starts an episode; with ``seed``, its initial state depends only on (task, seed).
        ``options={"idle": True}``: sit a batch step out (see ``stepnft.envs.base``)."""
        if options and options.get("idle"):
            if self._state is None:
                self._state = np.zeros(STATE_DIM, dtype=np.float32)
                if self.cameras:
                    self._image = np.zeros(self.observation_space["image"].shape, dtype=np.uint8)
            self._start_episode(idle=True)
            return self._obs(), self._info(steps=0)
        super().reset(seed=seed)
        # Always seeded: ManiSkill's unseeded reset would draw from torch's global RNG.
        episode_seed = int(self.np_random.integers(2**31)) if seed is None else maniskill_seed(seed)
        obs, _ = self._env.reset(seed=episode_seed)
        self._state = self._padded(obs)
        self._render_views()
        self._start_episode()
        return self._obs(), self._info(steps=0)

    def step(self, chunk: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Runs the rows of ``chunk`` [n_exec, 7] in order; see the class doc for the returns."""
        chunk = checked_chunk(chunk, self.action_space, self._state is not None)
        if self._ended:
            return self._obs(), 0.0, self._terminated, self._truncated, self._info(steps=0)
        reward_sum = 0.0
        steps = 0
        for action in np.clip(chunk, -1.0, 1.0).astype(np.float32):
            # ManiSkill's own truncation (its time limit, switched off above) is not used.
            obs, reward, _, _, sim_info = self._env.step(action)
            steps += 1
            reward_sum += float(reward)
            if self._count_step(bool(sim_info["success"])):
                break
        self._state = self._padded(obs)
        self._render_views()
        return self._obs(), reward_sum, self._terminated, self._truncated, self._info(steps)

    @staticmethod
    def _padded(obs: torch.Tensor) -> np.ndarray:
        state = np.zeros(STATE_DIM, dtype=np.float32)
        values = obs.reshape(-1).numpy()
        state[: len(values)] = values
        return state

    def _render_views(self) -> None:
        """Capture only the cameras asked for (ManiSkill's sensor observation renders them all,
        with depth) after hiding what ManiSkill hides from its cameras (e.g. PickCube's goal)."""
        if not self.cameras:
            return
        start = time.perf_counter()
        for obj in self._base._hidden_objects:
            obj.hide_visual()
        self._base.scene.update_render(update_sensors=True, update_human_render_cameras=False)
        views = []
        for name in self.cameras:
            sensor = self._base._sensors[name]
            sensor.capture()
            rgb = sensor.get_obs(rgb=True, depth=False, position=False, segmentation=False)["rgb"]
            views.append(rgb[0].permute(2, 0, 1).numpy())
        self._image = np.stack(views).astype(np.uint8)
        self.render_seconds += time.perf_counter() - start

    def _obs(self) -> dict[str, np.ndarray]:
        obs = {"state": self._state.copy()}
        if self.cameras:
            obs["image"] = self._image.copy()
        return obs

    def render(self) -> np.ndarray | None:
        """ManiSkill's video camera (``render_camera``), uint8 [height, width, 3], if built with
        ``render_size``."""
        if self.render_mode is None:
            return None
        return self._env.render()[0].numpy().astype(np.uint8)

    def close(self) -> None:
        self._env.close()
