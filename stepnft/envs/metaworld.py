"""MetaWorld v3 tasks as gymnasium envs whose action is a chunk of low-level actions.

`MetaWorldChunkEnv` is one task; `make_metaworld_vec_env` batches several tasks in one
`gymnasium.vector.SyncVectorEnv`. Observations are MetaWorld's 39-dim state with the goal
position visible (as in its MT benchmarks): hand xyz (0:3), gripper opening (3), object
poses (4:18), the same 18 values one step earlier (18:36), goal xyz (36:39).

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

from collections.abc import Sequence
from functools import partial
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode
from metaworld.env_dict import ALL_V3_ENVIRONMENTS
from metaworld.sawyer_xyz_env import SawyerXYZEnv

from stepnft.envs.instructions import instruction_for, unknown_task_error

OBS_DIM = 39
ACTION_DIM = 4
MAX_PATH_LENGTH = SawyerXYZEnv.max_path_length
"""MetaWorld raises if an episode is stepped past this many steps (500)."""

SIM_STEPS_PER_SECOND = 80
"""MetaWorld's control rate: 5 MuJoCo substeps of 2.5 ms per env step."""

TASK_NAMES: list[str] = sorted(ALL_V3_ENVIRONMENTS)


def validate_tasks(tasks: str | Sequence[str]) -> list[str]:
    """Checks MetaWorld v3 task names; `tasks` is a list or a comma-separated string."""
    if isinstance(tasks, str):
        tasks = [task.strip() for task in tasks.split(",") if task.strip()]
    tasks = list(tasks)
    if not tasks:
        raise ValueError(f"no MetaWorld task given; valid names: {', '.join(TASK_NAMES)}")
    for task in tasks:
        if task not in ALL_V3_ENVIRONMENTS:
            raise unknown_task_error(task, TASK_NAMES)
    return tasks


class MetaWorldChunkEnv(gym.Env):
    """One MetaWorld v3 task whose action is a chunk of `n_exec` actions, run in order.

    Observation: float32 [39]. Action: float32 [n_exec, 4] in [-1, 1] (xyz hand motion,
    gripper effort); rows are clipped to [-1, 1] before they reach the simulator.

    `step` stops early when the task succeeds (if `terminate_on_success`) or the episode
    reaches `max_episode_steps` env steps, and returns the summed reward and
    info = {"success": bool, success at any step of this episode so far;
            "steps": int, env steps run by this call; "episode_steps": int, since reset}.
    Truncation follows gymnasium's `TimeLimit`: at the limit `truncated` is True even if
    the same step succeeded. Stepping an episode that has ended leaves the simulator alone
    and returns the last observation, reward 0, the same flags and steps 0, so a batch with
    autoreset disabled can keep stepping its finished members.
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(
        self,
        task: str,
        n_exec: int = 4,
        max_episode_steps: int = 200,
        terminate_on_success: bool = True,
        seed: int = 0,
        render_mode: str | None = None,
        camera_name: str = "corner2",
        width: int = 224,
        height: int = 224,
    ):
        (self.task,) = validate_tasks([task])
        if n_exec < 1:
            raise ValueError(f"n_exec must be >= 1, got {n_exec}")
        if not 1 <= max_episode_steps <= MAX_PATH_LENGTH:
            raise ValueError(
                f"max_episode_steps must be in [1, {MAX_PATH_LENGTH}] (MetaWorld refuses to "
                f"step an episode past {MAX_PATH_LENGTH}), got {max_episode_steps}"
            )
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.instruction = instruction_for(self.task)
        self.n_exec = n_exec
        self.max_episode_steps = max_episode_steps
        self.terminate_on_success = terminate_on_success
        self.render_mode = render_mode
        # One rendered frame per chunk.
        self.metadata = {**self.metadata, "render_fps": SIM_STEPS_PER_SECOND / n_exec}

        # Every task reports a common unbounded space, so a vector env can mix tasks.
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n_exec, ACTION_DIM), np.float32)

        sim = ALL_V3_ENVIRONMENTS[self.task](
            render_mode=render_mode, camera_name=camera_name, width=width, height=height
        )
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
        self.np_random, _ = seeding.np_random(seed)

        self._obs: np.ndarray | None = None
        self._episode_steps = 0
        self._success = False
        self._terminated = False
        self._truncated = False

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Starts an episode; with `seed`, its initial state depends only on (task, seed)."""
        super().reset(seed=seed)
        # MetaWorld draws this episode's object and goal positions from our generator.
        self._sim.np_random = self.np_random
        obs, _ = self._sim.reset()
        self._obs = obs.astype(np.float32)
        self._episode_steps = 0
        self._success = False
        self._terminated = False
        self._truncated = False
        return self._obs.copy(), self._info(steps=0)

    def step(self, chunk: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Runs the rows of `chunk` [n_exec, 4] in order; see the class doc for the returns."""
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        chunk = np.asarray(chunk, dtype=np.float64)
        if chunk.shape != self.action_space.shape:
            raise ValueError(
                f"expected an action chunk of shape {self.action_space.shape}, got {chunk.shape}"
            )
        if self._terminated or self._truncated:
            return self._obs.copy(), 0.0, self._terminated, self._truncated, self._info(steps=0)

        reward_sum = 0.0
        steps = 0
        for action in np.clip(chunk, -1.0, 1.0):
            obs, reward, _, _, sim_info = self._sim.step(action)
            steps += 1
            self._episode_steps += 1
            reward_sum += float(reward)
            self._success = self._success or bool(sim_info["success"])
            self._terminated = self._success and self.terminate_on_success
            self._truncated = self._episode_steps >= self.max_episode_steps
            if self._terminated or self._truncated:
                break
        self._obs = obs.astype(np.float32)
        return self._obs.copy(), reward_sum, self._terminated, self._truncated, self._info(steps)

    def _info(self, steps: int) -> dict[str, Any]:
        return {"success": self._success, "steps": steps, "episode_steps": self._episode_steps}

    def render(self) -> np.ndarray | None:
        """The current camera image, uint8 [height, width, 3], if render_mode='rgb_array'."""
        if self.render_mode is None:
            return None
        # MetaWorld's offscreen images come out upside down.
        return np.ascontiguousarray(self._sim.render()[::-1])

    def close(self) -> None:
        self._sim.close()


class _MultiTaskLayout:
    """The task layout both vector envs share: sub-env i runs `tasks[i // envs_per_task]`.

    Sets `.tasks`, `.instructions` (per task), `.task_ids` [N], `.task_names` [N], then hands
    one env factory per sub-env to the gymnasium vector class it is mixed into.
    """

    def __init__(
        self,
        tasks: str | Sequence[str],
        envs_per_task: int = 1,
        n_exec: int = 4,
        max_episode_steps: int = 200,
        terminate_on_success: bool = True,
        seed: int = 0,
        autoreset: bool = True,
        **vector_kwargs: Any,
    ):
        self.tasks = validate_tasks(tasks)
        if len(set(self.tasks)) != len(self.tasks):
            raise ValueError(f"each task may appear once, got {', '.join(self.tasks)}")
        if envs_per_task < 1:
            raise ValueError(f"envs_per_task must be >= 1, got {envs_per_task}")
        self.instructions = [instruction_for(task) for task in self.tasks]
        self.task_ids = np.repeat(np.arange(len(self.tasks), dtype=np.int64), envs_per_task)
        self.task_names = [self.tasks[i] for i in self.task_ids]
        # Distinct, well-mixed sub-env seeds, so runs with nearby `seed`s share no streams.
        env_seeds = np.random.SeedSequence(seed).generate_state(len(self.task_names))
        env_fns = [
            partial(
                MetaWorldChunkEnv,
                task,
                n_exec=n_exec,
                max_episode_steps=max_episode_steps,
                terminate_on_success=terminate_on_success,
                seed=int(env_seed),
            )
            for task, env_seed in zip(self.task_names, env_seeds)
        ]
        mode = AutoresetMode.SAME_STEP if autoreset else AutoresetMode.DISABLED
        super().__init__(env_fns, autoreset_mode=mode, **vector_kwargs)


class MetaWorldVecEnv(_MultiTaskLayout, gym.vector.SyncVectorEnv):
    """Several MetaWorld tasks in one batch; sub-env i runs `tasks[i // envs_per_task]`.

    Build it with `make_metaworld_vec_env`. Observations [N, 39]; actions [N, n_exec, 4].

    autoreset=True (training) uses gymnasium's SAME_STEP mode: a sub-env whose episode
    ends is reset within the same `step`, so the returned observation and top-level
    info (success False, episode_steps 0) are already the next episode's. The ended
    episode's info is at `info["final_info"]` with mask `info["_final_info"]` [N]; its
    success is `info["final_info"]["success"][i]` for each i where the mask is True (and
    its last observation is `info["final_obs"][i]`).

    autoreset=False (evaluation) uses DISABLED: call `reset(seed=[s_0, ..., s_{N-1}])`
    for chosen initial states, then step until `terminated | truncated` holds everywhere;
    finished sub-envs keep answering with no-ops, and top-level `info["success"]` is each
    episode's result.
    """

    def step(self, actions: np.ndarray):
        if self.autoreset_mode == AutoresetMode.DISABLED:
            # SyncVectorEnv refuses to step a finished sub-env when autoreset is disabled;
            # ours treat that step as a no-op, so evaluation can step the whole batch.
            self._autoreset_envs[:] = False
        return super().step(actions)


class MetaWorldAsyncVecEnv(_MultiTaskLayout, gym.vector.AsyncVectorEnv):
    """`MetaWorldVecEnv` with each sub-env in its own process, at most `num_workers` stepping
    at once (MuJoCo is CPU-bound: one worker per core). Same arguments, layout, attributes and
    info keys; finished sub-envs answer steps with no-ops under autoreset disabled as well."""

    def __init__(self, *args: Any, num_workers: int = 2, **kwargs: Any):
        super().__init__(*args, max_concurrency=num_workers, context="fork", **kwargs)


def get_rng_states(venv) -> list[dict]:
    """Each sub-env's RNG state (JSON-serialisable), for checkpoints."""
    return [rng.bit_generator.state for rng in venv.get_attr("np_random")]


def set_rng_states(venv, states: list[dict]) -> None:
    """Restore what :func:`get_rng_states` returned: unseeded resets then continue the same streams."""
    rngs = []
    for state in states:
        rng = np.random.Generator(np.random.PCG64())
        rng.bit_generator.state = state
        rngs.append(rng)
    venv.set_attr("np_random", rngs)


def make_metaworld_vec_env(
    tasks: str | Sequence[str],
    envs_per_task: int = 1,
    n_exec: int = 4,
    max_episode_steps: int = 200,
    terminate_on_success: bool = True,
    seed: int = 0,
    autoreset: bool = True,
    num_workers: int = 0,
) -> MetaWorldVecEnv | MetaWorldAsyncVecEnv:
    """A batch of `len(tasks) * envs_per_task` MetaWorld chunk envs; see `MetaWorldVecEnv`.

    `num_workers` 0 steps every sub-env in this process; >= 1 uses one process per sub-env
    with at most `num_workers` running at once (`MetaWorldAsyncVecEnv`).
    """
    layout = dict(envs_per_task=envs_per_task, n_exec=n_exec, max_episode_steps=max_episode_steps,
                  terminate_on_success=terminate_on_success, seed=seed, autoreset=autoreset)
    if num_workers > 0:
        return MetaWorldAsyncVecEnv(tasks, num_workers=num_workers, **layout)
    return MetaWorldVecEnv(tasks, **layout)
