"""Scripted experts for ManiSkill tasks: privileged-state controllers of stepnft's own.

ManiSkill's demonstrations come from its motion planner (mplib 0.1.1), which crashes with the
numpy 2 that stepnft pins, and its published trajectories are downloads. These experts read the
object, goal and TCP poses from the ``state`` observation (privileged information, as MetaWorld's
scripted policies do) and emit ``pd_ee_delta_pose`` actions: a proportional move towards the
current phase's target, the gripper turned to the cube's faces, the gripper command. Like
MetaWorld's they keep no memory: the phase follows from the state alone, so one expert serves
any number of episodes. Success rates over 20 seeds are in docs/maniskill.md.
"""

from __future__ import annotations

import numpy as np

from stepnft.envs.base import Expert
from stepnft.envs.maniskill.tasks import STATE_LAYOUTS

OPEN, CLOSED = 1.0, -1.0
MAX_MOVE = 0.1
"""Metres per step of a full translation action (``pd_ee_delta_pose``); rotation: 0.1 rad."""
GAIN = 0.8
"""Fraction of the remaining error commanded per step (1 overshoots with the PD controller's lag)."""
CUBE_HALF = 0.02
"""Half the side of ManiSkill's cubes (m)."""


def _quat_yaw(q: np.ndarray) -> float:
    """Rotation about the world z-axis of a wxyz quaternion (the heading of its x-axis)."""
    w, x, y, z = q
    return float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def _wrap(angle: float, period: float) -> float:
    """``angle`` wrapped into [-period / 2, period / 2)."""
    return (angle + period / 2) % period - period / 2


class _StateExpert(Expert):
    """Reads named fields of one task's state (``tasks.STATE_LAYOUTS``)."""

    task: str

    def __init__(self):
        self._layout = STATE_LAYOUTS[self.task]

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        state = np.asarray(obs["state"], dtype=np.float64)
        return self.policy({name: state[part] for name, part in self._layout.items()})

    def policy(self, s: dict[str, np.ndarray]) -> np.ndarray:
        raise NotImplementedError

    @staticmethod
    def action(tcp: np.ndarray, target: np.ndarray | None, gripper: float, yaw_error: float = 0.0) -> np.ndarray:
        """Move a ``GAIN`` share of the way to ``target`` (None: hold still), turn by ``yaw_error``."""
        move = np.zeros(3) if target is None else GAIN * (target - tcp) / MAX_MOVE
        # The TCP points down: turning it by +a about its own z turns its heading by -a.
        turn = np.array([0.0, 0.0, -GAIN * yaw_error / MAX_MOVE])
        return np.clip(np.concatenate([move, turn, [gripper]]), -1.0, 1.0)

    @staticmethod
    def grasp_yaw_error(tcp_pose: np.ndarray, cube_pose: np.ndarray) -> float:
        """The turn (rad) that lines the fingers up with the nearest pair of the cube's faces."""
        return _wrap(_quat_yaw(cube_pose[3:]) - _quat_yaw(tcp_pose[3:]), np.pi / 2)

    def pick(self, tcp_pose: np.ndarray, cube_pose: np.ndarray, fingers: np.ndarray) -> np.ndarray:
        """Above the cube with the gripper open and turned to its faces, down, close."""
        tcp, cube = tcp_pose[:3], cube_pose[:3]
        yaw = self.grasp_yaw_error(tcp_pose, cube_pose)
        xy_off = np.linalg.norm(tcp[:2] - cube[:2])
        if np.linalg.norm(tcp - cube) < 0.01:  # around the cube: close on it
            return self.action(tcp, cube, CLOSED)
        if fingers.sum() < 0.07:  # closed elsewhere (a missed grasp): open first
            return self.action(tcp, tcp + [0, 0, 0.02], OPEN)
        if xy_off > 0.01 or abs(yaw) > 0.05:
            return self.action(tcp, cube + [0, 0, 0.06], OPEN, yaw)
        return self.action(tcp, cube, OPEN, yaw)

    @staticmethod
    def holding(tcp: np.ndarray, cube: np.ndarray, fingers: np.ndarray) -> bool:
        """The cube is between the closed fingers (each finger about half the cube's side open)."""
        return np.linalg.norm(tcp - cube) < 0.02 and 0.03 < fingers.sum() < 0.045


class PickCubeExpert(_StateExpert):
    """Pick the cube, carry it to the goal point, hold still there (success needs a static arm)."""

    task = "PickCube-v1"

    def policy(self, s):
        tcp, cube, goal = s["tcp_pose"][:3], s["obj_pose"][:3], s["goal_pos"]
        if s["is_grasped"][0] > 0.5 and self.holding(tcp, cube, s["qpos"][7:9]):
            if np.linalg.norm(goal - cube) < 0.005:
                return self.action(tcp, None, CLOSED)
            return self.action(tcp, tcp + (goal - cube), CLOSED)
        return self.pick(s["tcp_pose"], s["obj_pose"], s["qpos"][7:9])


class StackCubeExpert(_StateExpert):
    """Pick the red cube, carry it above the green one, lower it on, let go."""

    task = "StackCube-v1"

    def policy(self, s):
        tcp, a, b = s["tcp_pose"][:3], s["cubeA_pose"][:3], s["cubeB_pose"][:3]
        fingers = s["qpos"][7:9]
        on_top = b + [0, 0, 2 * CUBE_HALF]
        placed = np.linalg.norm(a[:2] - b[:2]) < 0.01 and abs(a[2] - on_top[2]) < 0.006
        if placed and np.linalg.norm(tcp - a) < 0.03:  # let go and stay clear
            return self.action(tcp, a if fingers.sum() < 0.07 else a + [0, 0, 0.05], OPEN)
        if self.holding(tcp, a, fingers):
            # Over the green cube first, clear of it, then straight down onto it.
            above = on_top + [0, 0, 0.04]
            if np.linalg.norm(a[:2] - b[:2]) > 0.008:
                return self.action(tcp, tcp + (above - a), CLOSED, self.grasp_yaw_error(s["cubeA_pose"], s["cubeB_pose"]))
            return self.action(tcp, tcp + (on_top + [0, 0, 0.002] - a), CLOSED)
        return self.pick(s["tcp_pose"], s["cubeA_pose"], fingers)


class _SlideExpert(_StateExpert):
    """Slide the cube along x with the closed gripper: ``side`` -1 pushes from behind (+x),
    +1 reaches over it and pulls (-x)."""

    side: float

    def policy(self, s):
        tcp, cube, goal = s["tcp_pose"][:3], s["obj_pose"][:3], s["goal_pos"]
        contact = cube + [self.side * (CUBE_HALF + 0.015), 0, 0]  # the TCP against the cube's face
        contact[2] = CUBE_HALF
        if np.linalg.norm(tcp[:2] - contact[:2]) > 0.015 or tcp[2] > CUBE_HALF + 0.02:
            if np.linalg.norm(tcp[:2] - contact[:2]) > 0.015:  # travel above the cube's height
                return self.action(tcp, contact + [0, 0, 0.07], CLOSED)
            return self.action(tcp, contact, CLOSED)
        # Against the cube: move it towards the goal's centre, steering in y.
        target = tcp + np.array([goal[0] - cube[0], goal[1] - cube[1], contact[2] - tcp[2]])
        return self.action(tcp, target, CLOSED)


class PushCubeExpert(_SlideExpert):
    task = "PushCube-v1"
    side = -1.0


class PullCubeExpert(_SlideExpert):
    task = "PullCube-v1"
    side = 1.0


EXPERTS: dict[str, type[_StateExpert]] = {
    cls.task: cls for cls in (PickCubeExpert, PushCubeExpert, PullCubeExpert, StackCubeExpert)}
"""Scripted experts by task."""
