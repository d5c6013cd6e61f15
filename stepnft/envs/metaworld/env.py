"""One MetaWorld v3 task as a chunk env (see ``stepnft.envs.base`` for the contract).

Observations: ``state`` is MetaWorld's 39-dim vector with the goal position visible (as in its
MT benchmarks): hand xyz (0:3), gripper opening (3), object poses (4:18), the same 18 values
one step earlier (18:36), goal xyz (36:39).

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

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding
from metaworld.env_dict import ALL_V3_ENVIRONMENTS
from metaworld.sawyer_xyz_env import SawyerXYZEnv

from stepnft.envs.base import RenderingError
from stepnft.envs.metaworld.instructions import instruction_for, unknown_task_error

OBS_DIM = 39
ACTION_DIM = 4
MAX_PATH_LENGTH = SawyerXYZEnv.max_path_length
"""MetaWorld raises if an episode is stepped past this many steps (500)."""

SIM_STEPS_PER_SECOND = 80
"""MetaWorld's control rate: 5 MuJoCo substeps of 2.5 ms per env step."""

TASK_NAMES: list[str] = sorted(ALL_V3_ENVIRONMENTS)

CAMERA = "corner2"
"""The camera of videos (MetaWorld renders it upside down; frames are flipped upright)."""


class MetaWorldChunkEnv(gym.Env):
    """One MetaWorld v3 task whose action is a chunk of `n_exec` actions, run in order.

    Observation: {"state": float32 [39]}. Action: float32 [n_exec, 4] in [-1, 1] (xyz hand
    motion, gripper effort); rows are clipped to [-1, 1] before they reach the simulator.

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
        self.task = task
        self.instruction = instruction_for(task)
        self.n_exec = n_exec
        self.max_episode_steps = max_episode_steps
        self.terminate_on_success = terminate_on_success
        self.render_mode = "rgb_array" if render_size else None
        self.metadata = {**self.metadata, "render_fps": SIM_STEPS_PER_SECOND}

        # Every task reports a common unbounded space, so a vector env can mix tasks.
        state_space = gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
        self.observation_space = gym.spaces.Dict({"state": state_space})
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n_exec, ACTION_DIM), np.float32)

        height, width = render_size or (224, 224)
        sim = ALL_V3_ENVIRONMENTS[task](render_mode=self.render_mode, camera_name=CAMERA, width=width, height=height)
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
        self._renderer_ready = False
        self.np_random, _ = seeding.np_random(seed)

        self._state: np.ndarray | None = None
        self._episode_steps = 0
        self._success = False
        self._terminated = False
        self._truncated = False

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Starts an episode; with `seed`, its initial state depends only on (task, seed).
        ``options={"idle": True}``: sit this wave out (see ``stepnft.envs.base``)."""
        if options and options.get("idle"):
            if self._state is None:
                self._state = np.zeros(OBS_DIM, dtype=np.float32)
            self._episode_steps, self._success, self._terminated, self._truncated = 0, False, False, True
            return self._obs(), self._info(steps=0)
        super().reset(seed=seed)
        # MetaWorld draws this episode's object and goal positions from our generator.
        self._sim.np_random = self.np_random
        state, _ = self._sim.reset()
        self._state = state.astype(np.float32)
        self._episode_steps = 0
        self._success = False
        self._terminated = False
        self._truncated = False
        return self._obs(), self._info(steps=0)

    def step(self, chunk: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Runs the rows of `chunk` [n_exec, 4] in order; see the class doc for the returns."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        chunk = np.asarray(chunk, dtype=np.float64)
        if chunk.shape != self.action_space.shape:
            raise ValueError(
                f"expected an action chunk of shape {self.action_space.shape}, got {chunk.shape}"
            )
        if self._terminated or self._truncated:
            return self._obs(), 0.0, self._terminated, self._truncated, self._info(steps=0)

        reward_sum = 0.0
        steps = 0
        for action in np.clip(chunk, -1.0, 1.0):
            state, reward, _, _, sim_info = self._sim.step(action)
            steps += 1
            self._episode_steps += 1
            reward_sum += float(reward)
            self._success = self._success or bool(sim_info["success"])
            self._terminated = self._success and self.terminate_on_success
            self._truncated = self._episode_steps >= self.max_episode_steps
            if self._terminated or self._truncated:
                break
        self._state = state.astype(np.float32)
        return self._obs(), reward_sum, self._terminated, self._truncated, self._info(steps)

    def _obs(self) -> dict[str, np.ndarray]:
        return {"state": self._state.copy()}

    def _info(self, steps: int) -> dict[str, Any]:
        return {"success": self._success, "steps": steps, "episode_steps": self._episode_steps}

    def render(self) -> np.ndarray | None:
        """The camera image, uint8 [height, width, 3] upright, if built with `render_size`."""
        if self.render_mode is None:
            return None
        if not self._renderer_ready:
            self._prepare_renderer()
        # MetaWorld's offscreen images come out upside down.
        return np.ascontiguousarray(self._sim.render()[::-1])

    def _prepare_renderer(self) -> None:
        """Create the offscreen viewer and turn shadows and reflections off (about 3x faster)."""
        import mujoco

        try:
            self._sim.render()
        except Exception as err:  # noqa: BLE001 - GL failures come as several error types
            raise RenderingError(f"offscreen rendering failed ({str(err).splitlines()[0]}): set MUJOCO_GL=egl "
                                 "and install libegl1 libegl-mesa0 (scripts/bootstrap.sh does)") from err
        # MetaWorld's gymnasium MujocoRenderer keeps the viewer it made for "rgb_array" in `.viewer`.
        scene = self._sim.mujoco_renderer.viewer.scn
        scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._renderer_ready = True

    def close(self) -> None:
        self._sim.close()
