"""One LIBERO task as a chunk env (see ``stepnft.envs.base`` for the contract).

The scene is LIBERO's robosuite environment (``ControlEnv``: a Panda arm with the
OSC_POSE controller at 20 Hz) built from the task's BDDL definition; success is the task's goal
predicate (``_check_success``), evaluated after every env step.

Observations:
    ``state``  float32 [8] with ``state_obs="proprio"``: end-effector position (3), orientation as
               an axis-angle (3), gripper finger positions (2): the proprioception of LIBERO's
               datasets (``ee_pos``, ``ee_ori``, ``gripper_states``) and of LeRobot's LIBERO
               datasets. With ``state_obs="full"`` (the default) float32 [64]: that, then the
               pose of each of the task's objects (position (3), quaternion xyzw (4); the task's
               objects of interest first, then the others in the BDDL file's order; zeros in
               the slots of a task with fewer than 8 objects), what a state policy needs to see
               where things are (the fixtures' joints, e.g. a drawer's, are not included). With
               ``state_obs="interest"`` float32 [22]: the proprioception and the first two
               slots only (the objects of interest: what is moved and where it goes); the other
               objects' poses let a few demonstrations be overfit (docs/libero.md)
    ``image``  uint8 [V, 3, S, S] with ``cameras`` (``agentview``, ``robot0_eye_in_hand``), S =
               ``image_size``: upright (rotated 180 degrees from robosuite's raw frame, as OpenVLA
               and LeRobot feed it), with shadows, as LIBERO's datasets were rendered
Cameras are rendered once per ``step`` call (after the chunk), not after every env step.

Reward: ``reward="sparse"`` (LIBERO's own): per env step 1 while the goal holds, else 0.
``reward="shaped"``: robosuite's staged pick-and-place reward (its PickPlace task's reach 0.1,
grasp 0.35, lift 0.5, hover 0.7 stages; :func:`staged_reward`) for the first object of interest
(what is moved) and the second (where it goes), 1 once the goal holds: a function of the state
that rises as the episode gets closer to success, which π-StepNFT's ``labels: progress`` and
PPO's ``reward: shaped`` read. Only for tasks with two objects of interest that are objects (the
pick-and-place tasks of libero_object and libero_spatial, some of libero_goal and libero_10).

Actions: float32 [n_exec, 7] in [-1, 1]: end-effector translation (3) and rotation (3) deltas,
gripper (-1 open, +1 close), as in LIBERO's datasets.

Initial states. Each task has 50 fixed initial states (LIBERO's ``.pruned_init`` files);
``reset(seed=s)`` starts from state ``s % 50``, so evaluation episodes 0..49 are exactly LIBERO's
evaluation protocol. An unseeded reset draws the state from the env's own stream. The scene is
reset (its random object placement drawn from a generator seeded by the state index, then
overwritten by the initial state), the state is set, and ``settle_steps`` no-op actions (gripper
open) let objects settle, as the reference evaluation does; they do not count as episode steps.
LIBERO has no perturbation suites (``perturbations`` are refused).
``reset(options={"init_state": flat_state})`` starts exactly from any flattened MuJoCo state of
the task, without settling steps (e.g. a state of a recorded demonstration). Replaying recorded
actions from there can drift: the gripper's command ramp is not part of MuJoCo's state.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding

from stepnft.envs.base import ChunkEpisode, RenderingError, checked_chunk
from stepnft.envs.libero.suites import all_tasks, initial_states

STATE_DIM = 8
"""The proprioception (``state_obs="proprio"``)."""
OBJECT_SLOTS = 8
"""Object poses in the full state: the most objects of any LIBERO task (libero_90 has 8)."""
FULL_STATE_DIM = STATE_DIM + 7 * OBJECT_SLOTS
"""The proprioception and the objects' poses (``state_obs="full"``)."""
INTEREST_SLOTS = 2
"""Object slots in the ``interest`` state: LIBERO's objects of interest (what is moved, where to)."""
STATE_DIMS = {"proprio": STATE_DIM, "interest": STATE_DIM + 7 * INTEREST_SLOTS, "full": FULL_STATE_DIM}
"""Size of each ``state_obs``; each is a prefix of the full state."""


def state_dim_for(state_obs: str) -> int:
    """Size of the state observation ``state_obs``, or a one-line error naming the choices."""
    if state_obs not in STATE_DIMS:
        raise ValueError(f"LIBERO's state_obs is full (proprioception and every object's pose), interest (and the "
                         f"objects of interest only) or proprio, got {state_obs!r}")
    return STATE_DIMS[state_obs]

ACTION_DIM = 7
CONTROL_HZ = 20
CAMERAS = ("agentview", "robot0_eye_in_hand")
"""LIBERO's cameras: the scene and the wrist (its datasets' ``agentview_rgb``, ``eye_in_hand_rgb``)."""
SETTLE_STEPS = 10
SETTLE_ACTION = np.array([0, 0, 0, 0, 0, 0, -1], dtype=np.float64)
"""Hold still with the gripper open (the reference evaluation's 'dummy action')."""


REWARDS = ("sparse", "shaped")
LIFT_HEIGHT = 0.25
"""The lift stage's target: this far above the place target (the scripted recorder's carry height)."""
ABOVE_TARGET = 0.05
"""Within this x and y distance of the place target the object counts as above it."""


def staged_reward(problem, moved, target) -> float:
    """robosuite's PickPlace staged reward for moving object ``moved`` to ``target`` (LIBERO
    objects of ``problem``, LIBERO's robosuite env): the largest of reaching (0.1 at the object),
    grasping (0.35), lifting towards ``LIFT_HEIGHT`` above the target (0.35 to 0.5, while
    grasped) and hovering over the target (0.5 to 0.7 once above it, else the lift reward plus up
    to 0.2 for closing in), in [0, 0.7]."""
    gripper = problem.robots[0].gripper
    obj = problem.sim.data.body_xpos[problem.obj_body_id[moved.name]]
    goal = problem.sim.data.body_xpos[problem.obj_body_id[target.name]]
    reach = 0.1 * (1 - np.tanh(10.0 * problem._gripper_to_target(gripper, moved.root_body, "body", True)))
    grasp = 0.35 * bool(problem._check_grasp(gripper, moved.contact_geoms))
    lift = 0.35 + 0.15 * (1 - np.tanh(15.0 * max(goal[2] + LIFT_HEIGHT - obj[2], 0.0))) if grasp else 0.0
    xy = np.abs(obj[:2] - goal[:2])
    closer = 1 - np.tanh(10.0 * float(np.linalg.norm(xy)))
    hover = (0.5 if (xy < ABOVE_TARGET).all() else lift) + 0.2 * closer
    return float(max(reach, grasp, lift, hover))


def proprio_state(obs: dict[str, np.ndarray]) -> np.ndarray:
    """The 8-d ``state`` from robosuite's observation dict."""
    from robosuite.utils.transform_utils import quat2axisangle

    return np.concatenate([obs["robot0_eef_pos"], quat2axisangle(obs["robot0_eef_quat"]),
                           obs["robot0_gripper_qpos"]]).astype(np.float32)


def object_names(problem) -> list[str]:
    """The task's objects in the full state's order: its objects of interest first, then the
    others as the BDDL file lists them (``problem``: LIBERO's problem env)."""
    first = [name for name in problem.obj_of_interest if name in problem.objects_dict]
    return first + [name for name in problem.objects_dict if name not in first]


def object_poses(obs: dict[str, np.ndarray], names: Sequence[str]) -> np.ndarray:
    """float32 [7 * OBJECT_SLOTS]: position and quaternion of each object of ``names`` from
    robosuite's observation dict, zero-padded."""
    poses = np.zeros((OBJECT_SLOTS, 7), dtype=np.float32)
    for slot, name in enumerate(names[:OBJECT_SLOTS]):
        poses[slot] = np.concatenate([obs[f"{name}_pos"], obs[f"{name}_quat"]])
    return poses.reshape(-1)


class LiberoChunkEnv(ChunkEpisode, gym.Env):
    """One LIBERO task whose action is a chunk of ``n_exec`` actions, run in order (module doc).

    ``step`` stops early when the task succeeds (if ``terminate_on_success``) or the episode
    reaches its cap: ``max_episode_steps``, at most the suite's reference cap. It returns the
    summed reward (``reward``: see the module doc) and info (``success``,
    ``steps``, ``episode_steps``). Stepping an ended episode is a no-op.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}

    def __init__(self, task: str, n_exec: int = 1, max_episode_steps: int = 520, terminate_on_success: bool = True,
                 seed: int = 0, render_size: tuple[int, int] | None = None, cameras: Sequence[str] = (),
                 image_size: int = 64, state_obs: str = "full", perturbations=None, settle_steps: int = SETTLE_STEPS,
                 reward: str = "sparse"):
        tasks = all_tasks()
        if task not in tasks:
            raise ValueError(f"unknown LIBERO task {task!r}: `python -m stepnft.envs.libero` lists them")
        if n_exec < 1 or max_episode_steps < 1 or image_size < 1 or settle_steps < 0:
            raise ValueError(f"need n_exec >= 1, max_episode_steps >= 1, image_size >= 1 and settle_steps >= 0, got "
                             f"{n_exec}, {max_episode_steps}, {image_size}, {settle_steps}")
        unknown = [c for c in cameras if c not in CAMERAS]
        if unknown:
            raise ValueError(f"unknown LIBERO camera {unknown[0]!r}; its cameras: {', '.join(CAMERAS)}")
        state_dim = state_dim_for(state_obs)
        if reward not in REWARDS:
            raise ValueError(f"LIBERO's reward is sparse (its own) or shaped, got {reward!r}")
        if perturbations:
            raise ValueError("LIBERO has no perturbation suites or training randomisation (docs/ood.md is MetaWorld's)")
        self.task = tasks[task]
        self.instruction = self.task.instruction
        self.n_exec = n_exec
        self.max_episode_steps = min(max_episode_steps, self.task.max_episode_steps)
        self.terminate_on_success = terminate_on_success
        self.render_size = render_size
        self.render_mode = "rgb_array" if render_size else None
        self.settle_steps = settle_steps
        self._cameras = list(cameras)
        self._image_size = image_size
        self._init_states = initial_states(task)
        self.state_obs = state_obs

        spaces = {"state": gym.spaces.Box(-np.inf, np.inf, (state_dim,), np.float32)}
        if self._cameras:
            spaces["image"] = gym.spaces.Box(0, 255, (len(self._cameras), 3, image_size, image_size), np.uint8)
        self.observation_space = gym.spaces.Dict(spaces)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n_exec, ACTION_DIM), np.float32)

        from libero.libero.envs.env_wrapper import ControlEnv

        # No robosuite camera observations (they would render every camera after every env
        # step): the cameras are rendered here, once per call, and a GL context is made only
        # if something is rendered (none for a state-only env; EGL does not survive a fork). A
        # soft reset (hard_reset=False) keeps the compiled model instead of rebuilding it from
        # XML (seconds) at every reset.
        self._env = ControlEnv(bddl_file_name=self.task.bddl_file, use_camera_obs=False,
                               has_offscreen_renderer=bool(self._cameras or render_size), has_renderer=False,
                               camera_names=[CAMERAS[0]], camera_heights=image_size,
                               camera_widths=image_size, hard_reset=False, ignore_done=True,
                               control_freq=CONTROL_HZ)
        self._objects = object_names(self._env.env)
        self._staged = None
        if reward == "shaped":
            problem = self._env.env
            interest = [problem.objects_dict.get(name) for name in problem.obj_of_interest[:2]]
            if len(interest) < 2 or None in interest:
                raise ValueError(f"LIBERO's shaped reward is for pick-and-place tasks (two objects of interest: what is "
                                 f"moved, where it goes); {task} has {list(problem.obj_of_interest)}: use reward sparse")
            self._staged = interest
        self.np_random, _ = seeding.np_random(seed)
        self._obs: dict[str, np.ndarray] | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Starts an episode from initial state ``seed % 50`` (see the module doc).
        ``options={"idle": True}``: sit a batch step out (see ``stepnft.envs.base``);
        ``{"placement": k}``: from LIBERO's own random object placement drawn with seed ``k``
        instead (the distribution the 50 states were drawn from, but none of them: for
        demonstrations that must not start where evaluation does); ``{"init_state": s}``: from
        the flattened MuJoCo state ``s``."""
        options = options or {}
        if options.get("idle"):
            if self._obs is None:
                self._obs = {k: np.zeros(space.shape, space.dtype) for k, space in self.observation_space.items()}
            self._start_episode(idle=True)
            return self._copy_obs(), self._info(steps=0)
        super().reset(seed=seed)
        index = seed % len(self._init_states) if seed is not None else int(self.np_random.integers(len(self._init_states)))
        state = options.get("init_state", self._init_states[index])
        placement = options.get("placement")
        # LIBERO's reset draws object placements from numpy's global generator; the initial state
        # overwrites them, but seed it anyway (and restore it) so nothing depends on the past.
        global_rng = np.random.get_state()
        np.random.seed(index if placement is None else int(placement))
        try:
            raw = self._env.reset()
        finally:
            np.random.set_state(global_rng)
        for robot in self._env.robots:  # a soft reset leaves the gripper's command ramp where it was
            robot.gripper.current_action = np.zeros(robot.gripper.dof)
        if placement is None:
            raw = self._env.set_init_state(np.asarray(state, dtype=np.float64))
        for _ in range(0 if "init_state" in options else self.settle_steps):
            raw, _, _, _ = self._env.step(SETTLE_ACTION)
        self._start_episode()
        self._obs = self._observe(raw)
        return self._copy_obs(), self._info(steps=0)

    def step(self, chunk: np.ndarray):
        """Runs the rows of ``chunk`` [n_exec, 7] in order; see the class doc for the returns."""
        chunk = checked_chunk(chunk, self.action_space, self._obs is not None)
        if self._ended:
            return self._copy_obs(), 0.0, self._terminated, self._truncated, self._info(steps=0)
        reward_sum, steps = 0.0, 0
        for action in np.clip(chunk, -1.0, 1.0):
            raw, reward, goal_reached, _ = self._env.step(action)
            steps += 1
            if self._staged is not None:
                reward = 1.0 if goal_reached else staged_reward(self._env.env, *self._staged)
            reward_sum += float(reward)
            if self._count_step(bool(goal_reached)):
                break
        self._obs = self._observe(raw)
        return self._copy_obs(), reward_sum, self._terminated, self._truncated, self._info(steps)

    def sim_state(self) -> np.ndarray:
        """The flattened MuJoCo state (what LIBERO's datasets store as ``states``)."""
        return self._env.get_sim_state().copy()

    def full_states(self, sim_states: np.ndarray) -> np.ndarray:
        """float32 [T, 64]: the full ``state`` observation at each flattened MuJoCo state of this
        task (e.g. a recorded demonstration's ``states``). Leaves the env needing a reset."""
        rows = []
        for state in np.asarray(sim_states, dtype=np.float64):
            raw = self._env.regenerate_obs_from_state(state)
            rows.append(np.concatenate([proprio_state(raw), object_poses(raw, self._objects)]))
        self._obs = None
        return np.stack(rows).astype(np.float32)

    def _observe(self, raw: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        obs = {"state": proprio_state(raw)}
        if self.state_obs != "proprio":
            obs["state"] = np.concatenate([obs["state"], object_poses(raw, self._objects)])[: STATE_DIMS[self.state_obs]]
        if self._cameras:
            size = self._image_size
            obs["image"] = np.stack([self._render(camera, size, size).transpose(2, 0, 1) for camera in self._cameras])
        return obs

    def _copy_obs(self) -> dict[str, np.ndarray]:
        return {k: v.copy() for k, v in self._obs.items()}

    def _render(self, camera: str, height: int, width: int) -> np.ndarray:
        """uint8 [height, width, 3], upright. Shadows stay on (without them a frame takes about
        0.6x the time, but LIBERO's datasets were rendered with them)."""
        try:
            frame = self._env.sim.render(camera_name=camera, width=width, height=height)
        except Exception as err:  # noqa: BLE001 - GL failures come as several error types
            raise RenderingError(f"offscreen rendering failed ({str(err).splitlines()[0]}): set MUJOCO_GL=egl "
                                 "and install libegl1 libegl-mesa0 (scripts/bootstrap.sh does)") from err
        return np.ascontiguousarray(frame[::-1, ::-1])  # robosuite's frames come out rotated by 180 degrees

    def render(self) -> np.ndarray | None:
        """The agentview camera at ``render_size``, uint8 [h, w, 3] upright, if built with one."""
        if self.render_size is None:
            return None
        return self._render(CAMERAS[0], *self.render_size)

    def close(self) -> None:
        if getattr(self, "_env", None) is not None:
            self._env.close()  # frees the GL context now; MuJoCo's EGL complains if left to __del__
            self._env = None
