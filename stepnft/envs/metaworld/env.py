"""One MetaWorld v3 task as a chunk env (see ``stepnft.envs.base`` for the contract).

Observations: ``state`` is MetaWorld's 39-dim vector with the goal position visible (as in its
MT benchmarks): hand xyz (0:3), gripper opening (3), object poses (4:18), the same 18 values
one step earlier (18:36), goal xyz (36:39); with ``state_obs="proprio"`` only the hand xyz and
gripper opening (0:4), for camera policies. With ``cameras``, ``image`` holds uint8
[V, 3, size, size] upright images, rendered once per ``step`` call (after the chunk) and at
reset, i.e. once per policy call, never per env step. Camera policies see the goal marker (the
``goal`` site, drawn at a radius of at least ``GOAL_MARKER_RADIUS``) of tasks whose goal is
random and not given by an object; tasks whose goal follows from an object (door, drawer,
button, ...) show that object. With semantic perturbations, ``instruction`` (int64) is the index
of the episode's instruction variant (``MetaWorld.instruction_variants``).

Deterministic initial states. Each MetaWorld env draws its object and goal positions (its
"rand vec") inside `reset_model()`: from `env.np_random` when `seeded_rand_vec` is set, else
from numpy's global RNG, unless `_freeze_rand_vec` pins one vector chosen by `set_task()`.
`gym.make("Meta-World/MT1", ...)` pins 50 goals pre-drawn from the seed given at make and
picks one per reset with a wrapper RNG; its `reset(seed=...)` reseeds none of them. Here we
build the task's class directly, unpin the rand vec and draw it from this env's `np_random`,
which `reset(seed=s)` reseeds (gymnasium's rule). MuJoCo's state is cleared at every reset
(`mj_resetData`, then the hand is driven to its fixed start pose), so the initial state
depends only on (task, s); this was checked for all 50 tasks, whatever ran before.
An unseeded reset continues the env's stream (seeded at construction, or by the last
`reset(seed=...)`).
"""

import time
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding
from metaworld.env_dict import ALL_V3_ENVIRONMENTS
from metaworld.sawyer_xyz_env import SawyerXYZEnv

from stepnft.envs.base import ChunkEpisode, checked_chunk
from stepnft.envs.metaworld.camera import CameraRenderer
from stepnft.envs.metaworld.instructions import instruction_for, task_instruction_variants, unknown_task_error
from stepnft.envs.metaworld.perturb import ModelPerturber
from stepnft.envs.perturbations import Perturbations

OBS_DIM = 39
ACTION_DIM = 4
MAX_PATH_LENGTH = SawyerXYZEnv.max_path_length
"""MetaWorld raises if an episode is stepped past this many steps (500)."""

SIM_STEPS_PER_SECOND = 80
"""MetaWorld's control rate: 5 MuJoCo substeps of 2.5 ms per env step."""

TASK_NAMES: list[str] = sorted(ALL_V3_ENVIRONMENTS)

CAMERA = "corner2"
"""The camera of videos (MetaWorld mounts it upside down; frames are turned upright)."""

PROPRIO_DIM = 4
"""Hand xyz and gripper opening: the state of ``state_obs="proprio"``."""

STATE_OBS = {"full": OBS_DIM, "proprio": PROPRIO_DIM}
"""State observation choices and their sizes."""

GOAL_MARKER_RADIUS = 0.03
"""Smallest radius (m) of the goal marker in observation images: MetaWorld's 1-2 cm sphere
covers about one pixel at 64 px."""


class MetaWorldChunkEnv(ChunkEpisode, gym.Env):
    """One MetaWorld v3 task whose action is a chunk of `n_exec` actions, run in order.

    Observation: {"state": float32 [39] (or [4] with ``state_obs="proprio"``), with ``cameras``
    "image": uint8 [V, 3, image_size, image_size], with semantic perturbations "instruction":
    int64}. Action: float32 [n_exec, 4] in [-1, 1] (xyz hand motion, gripper effort); rows are
    clipped to [-1, 1] before they reach the simulator. ``perturbations`` shift each episode's
    scene, dynamics or instruction (``stepnft.envs.perturbations``).

    `step` stops early when the task succeeds (if `terminate_on_success`) or the episode
    reaches `max_episode_steps` env steps, and returns the summed reward and info
    (``success``, ``steps``, ``episode_steps``). Truncation follows gymnasium's `TimeLimit`: at
    the limit `truncated` is True even if the same step succeeded. Stepping an ended episode
    is a no-op (see ``stepnft.envs.base``).
    """

    metadata = {"render_modes": ["rgb_array"]}

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
        perturbations: Perturbations | None = None,
    ):
        if task not in ALL_V3_ENVIRONMENTS:
            raise unknown_task_error(task, TASK_NAMES)
        if n_exec < 1:
            raise ValueError(f"n_exec must be >= 1, got {n_exec}")
        if not 1 <= max_episode_steps <= MAX_PATH_LENGTH:
            raise ValueError(
                f"max_episode_steps must be in [1, {MAX_PATH_LENGTH}] (MetaWorld refuses to "
                f"step an episode past {MAX_PATH_LENGTH}), got {max_episode_steps}"
            )
        if state_obs not in STATE_OBS:
            raise ValueError(f"state_obs must be one of {', '.join(STATE_OBS)}, got {state_obs!r}")
        if cameras and not 8 <= image_size <= 480:
            raise ValueError(f"image_size must be in [8, 480], got {image_size}")
        self.task = task
        self.instruction = instruction_for(task)
        self.perturbations = perturbations or Perturbations()
        self.instructions, self._instruction_segments = task_instruction_variants(task, self.perturbations)
        self.state_obs = state_obs
        self.n_exec = n_exec
        self.max_episode_steps = max_episode_steps
        self.terminate_on_success = terminate_on_success
        self.render_mode = "rgb_array" if render_size else None
        self.metadata = {**self.metadata, "render_fps": SIM_STEPS_PER_SECOND}

        # Every task reports a common unbounded space, so a vector env can mix tasks.
        spaces = {"state": gym.spaces.Box(-np.inf, np.inf, (STATE_OBS[state_obs],), np.float32)}
        if cameras:
            spaces["image"] = gym.spaces.Box(0, 255, (len(cameras), 3, image_size, image_size), np.uint8)
        if self.perturbations.semantic:
            spaces["instruction"] = gym.spaces.Box(0, np.iinfo(np.int32).max, (), np.int64)
        self.observation_space = gym.spaces.Dict(spaces)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n_exec, ACTION_DIM), np.float32)

        # MetaWorld's own renderer stays off: CameraRenderer draws observations and video frames.
        sim = ALL_V3_ENVIRONMENTS[task]()
        # Show the goal, as MetaWorld's MT benchmarks do. The cached observation space was
        # built for the hidden goal and `sim.step` clips observations to it, so drop it.
        sim._partially_observable = False
        del sim.sawyer_observation_space
        # Draw object and goal positions at every reset from `sim.np_random` (see module doc)
        # instead of requiring `set_task()` and its pinned goal.
        sim._set_task_called = True
        sim._freeze_rand_vec = False
        sim.seeded_rand_vec = True
        self._sim = sim
        self._render_size = render_size
        self._video_camera: CameraRenderer | None = None
        self._cameras: CameraRenderer | None = None
        if cameras:
            goal = [i for i in range(sim.model.nsite) if sim.model.site(i).name == "goal"]
            sim.model.site_size[goal, 0] = np.maximum(sim.model.site_size[goal, 0], GOAL_MARKER_RADIUS)
            self._cameras = CameraRenderer(sim.model, cameras, image_size, image_size)
        self._perturber = ModelPerturber(sim) if self.perturbations else None
        self.np_random, _ = seeding.np_random(seed)

        self._state: np.ndarray | None = None
        self._image: np.ndarray | None = None
        self._instruction = 0
        self.render_seconds = 0.0
        """Time spent rendering observation images since construction (benchmarks read it)."""
        self.episode_perturbations: dict[str, dict] = {}
        """The parameters of this episode's perturbations (``Perturbations.sample``)."""
        self._action_noise: tuple[np.random.Generator, float] | None = None

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Starts an episode; with `seed`, its initial state depends only on (task, seed).
        ``options={"idle": True}``: sit a batch step out (see ``stepnft.envs.base``)."""
        if options and options.get("idle"):
            if self._state is None:
                self._state = np.zeros(OBS_DIM, dtype=np.float32)
                if self._cameras is not None:
                    self._image = np.zeros(self.observation_space["image"].shape, dtype=np.uint8)
            self._start_episode(idle=True)
            return self._obs(), self._info(steps=0)
        super().reset(seed=seed)
        if self._perturber is not None:
            self._perturb(seed)
        # MetaWorld draws this episode's object and goal positions from our generator.
        self._sim.np_random = self.np_random
        state, _ = self._sim.reset()
        self._state = state.astype(np.float32)
        self._render_views()
        self._start_episode()
        return self._obs(), self._info(steps=0)

    def step(self, chunk: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Runs the rows of `chunk` [n_exec, 4] in order; see the class doc for the returns."""
        chunk = checked_chunk(chunk, self.action_space, self._state is not None)
        if self._ended:
            return self._obs(), 0.0, self._terminated, self._truncated, self._info(steps=0)

        reward_sum = 0.0
        steps = 0
        for action in np.clip(chunk, -1.0, 1.0):
            if self._action_noise is not None:
                rng, std = self._action_noise
                action = np.clip(action + rng.normal(0.0, std, size=action.shape), -1.0, 1.0)
            state, reward, _, _, sim_info = self._sim.step(action)
            steps += 1
            reward_sum += float(reward)
            if self._count_step(bool(sim_info["success"])):
                break
        self._state = state.astype(np.float32)
        self._render_views()
        return self._obs(), reward_sum, self._terminated, self._truncated, self._info(steps)

    def _perturb(self, seed: int | None) -> None:
        """Draw this episode's perturbations (from the reset seed) and apply them."""
        spec = self.perturbations
        rng = spec.episode_rng(seed, self.np_random)
        params = spec.sample(spec.episode_names(seed, rng), rng)
        self._perturber.apply(params)
        self._action_noise = (rng, params["action_noise"]["std"]) if "action_noise" in params else None
        self._instruction = spec.instruction_index(self._instruction_segments, len(self.instructions), params)
        self.episode_perturbations = params

    def _render_views(self) -> None:
        if self._cameras is not None:
            start = time.perf_counter()
            self._image = self._cameras.views(self._sim.data)
            self.render_seconds += time.perf_counter() - start

    def _obs(self) -> dict[str, np.ndarray]:
        obs = {"state": self._state[: self.observation_space["state"].shape[0]].copy()}
        if self._cameras is not None:
            obs["image"] = self._image.copy()
        if "instruction" in self.observation_space.spaces:
            obs["instruction"] = np.int64(self._instruction)
        return obs

    def render(self) -> np.ndarray | None:
        """The video camera's image (``CAMERA``), uint8 [height, width, 3] upright, if built
        with `render_size`."""
        if self.render_mode is None:
            return None
        if self._video_camera is None:
            self._video_camera = CameraRenderer(self._sim.model, [CAMERA], *self._render_size)
        return self._video_camera.frame(self._sim.data)

    def close(self) -> None:
        # Free the GL contexts now; MuJoCo's EGL complains if they are left to __del__.
        for renderer in (self._video_camera, self._cameras):
            if renderer is not None:
                renderer.close()
        self._video_camera = self._cameras = None
        self._sim.close()
