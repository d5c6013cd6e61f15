"""Gymnasium's MuJoCo Reacher (``Reacher-v5``) as a stepnft simulator.

A two-link planar arm brings its fingertip to a random target. stepnft needs three things a
Gymnasium env does not say by itself: what success is (here: the fingertip within
:data:`SUCCESS_RADIUS` of the target), an instruction per task, and a scripted expert for
demonstrations (here: inverse kinematics and a PD controller). The rest is the chunk-env
contract of ``stepnft.envs.base``: actions arrive in chunks of ``n_exec``, and episodes count
their own steps and success with ``ChunkEpisode``.

This module is what the ``stepnft.simulators`` entry point loads (``INFO``), so it imports
nothing heavy: MuJoCo and the Reacher env are imported when an env is built.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from stepnft.envs import SimulatorInfo
from stepnft.envs.base import ChunkEpisode, Expert, Simulator, checked_chunk

INFO = SimulatorInfo("stepnft_example.sim:Reacher", max_episode_steps=200, default_tasks=("reach",), reward="shaped",
                     opengl=True)
"""What stepnft checks before building anything: the longest episode, the default task, that
the env's own reward measures progress (Reacher's is minus the distance), and that it renders
through MuJoCo's OpenGL (stepnft then sets and checks ``MUJOCO_GL`` before MuJoCo is imported)."""

SUCCESS_RADIUS = 0.01
"""The fingertip within this distance (m) of the target is a success (the fingertip's own radius)."""
LINKS = (0.1, 0.11)
"""The arm's link lengths (Reacher's model): the expert's inverse kinematics."""


class ReacherChunkEnv(ChunkEpisode, gym.Env):
    """Observation ``{"state": Reacher's 10 features}``; action ``[n_exec, 2]`` joint torques."""

    def __init__(self, n_exec: int = 1, max_episode_steps: int = 50, terminate_on_success: bool = True,
                 seed: int = 0, render_size: tuple[int, int] | None = None):
        from gymnasium.envs.mujoco.reacher_v5 import ReacherEnv

        if render_size is None:
            self._env = ReacherEnv()
        else:
            self._env = ReacherEnv(render_mode="rgb_array", height=render_size[0], width=render_size[1])
        self.n_exec, self.max_episode_steps, self.terminate_on_success = n_exec, max_episode_steps, terminate_on_success
        self.observation_space = gym.spaces.Dict({"state": gym.spaces.Box(-np.inf, np.inf, (10,), np.float32)})
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n_exec, 2), np.float32)
        self._env.reset(seed=seed)  # seeds the env's stream: unseeded resets continue it
        self._obs: np.ndarray | None = None

    # The collector saves and restores every sub-env's stream (exact resume): it is the Reacher's.
    @property
    def np_random(self) -> np.random.Generator:
        return self._env.np_random

    @np_random.setter
    def np_random(self, value: np.random.Generator) -> None:
        self._env.np_random = value

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if options and options.get("idle"):  # sit a batch step out: no simulation, the stream untouched
            self._start_episode(idle=True)
            if self._obs is None:
                self._obs = np.zeros(10, dtype=np.float32)
            return {"state": self._obs.copy()}, self._info(0)
        obs, _ = self._env.reset(seed=seed)
        self._obs = obs.astype(np.float32)
        self._start_episode()
        return {"state": self._obs.copy()}, self._info(0)

    def step(self, chunk: np.ndarray):
        chunk = checked_chunk(chunk, self.action_space, self._obs is not None)
        if self._ended:
            return {"state": self._obs.copy()}, 0.0, self._terminated, self._truncated, self._info(0)
        reward, steps = 0.0, 0
        for action in np.clip(chunk, -1.0, 1.0):
            obs, r, _, _, _ = self._env.step(action.astype(np.float32))
            self._obs, reward, steps = obs.astype(np.float32), reward + float(r), steps + 1
            if self._count_step(bool(np.linalg.norm(obs[8:10]) < SUCCESS_RADIUS)):
                break
        return {"state": self._obs.copy()}, reward, self._terminated, self._truncated, self._info(steps)

    def render(self) -> np.ndarray:
        return self._env.render()

    def close(self) -> None:
        self._env.close()


class ReacherExpert(Expert):
    """Inverse kinematics to the target, then a PD controller on the joint angles (of the two
    arm poses that reach it, the one nearer the current pose); it reaches the target in about 8
    steps. ``noise`` adds Gaussian action noise from its own seeded stream."""

    def __init__(self, seed: int, kp: float = 1.0, kd: float = 0.05, noise: float = 0.0):
        self.kp, self.kd, self.noise = kp, kd, noise
        self._rng = np.random.default_rng(seed)

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        s = obs["state"].astype(np.float64)
        q, qvel, (x, y) = np.arctan2(s[2:4], s[0:2]), s[6:8], s[4:6]
        l1, l2 = LINKS
        cos2 = np.clip((x * x + y * y - l1 * l1 - l2 * l2) / (2 * l1 * l2), -1.0, 1.0)
        best = None
        for sign in (1.0, -1.0):
            q2 = sign * np.arccos(cos2)
            q1 = np.arctan2(y, x) - np.arctan2(l2 * np.sin(q2), l1 + l2 * np.cos(q2))
            error = np.angle(np.exp(1j * (np.array([q1, q2]) - q)))  # wrapped to (-pi, pi]
            if best is None or np.abs(error).sum() < np.abs(best).sum():
                best = error
        action = self.kp * best - self.kd * qvel
        return np.clip(action + self.noise * self._rng.standard_normal(2), -1.0, 1.0)


class Reacher(Simulator):
    name = "reacher"
    label = "Reacher (Gymnasium MuJoCo)"
    distribution = "gymnasium"  # the package whose version demonstrations record
    state_dim = 10
    action_dim = 2
    control_hz = 50.0  # Reacher steps 0.02 s of simulated time

    def task_names(self) -> list[str]:
        return ["reach"]

    def instruction(self, task: str) -> str:
        return "move the fingertip onto the red target"

    def make_env(self, task, n_exec=1, max_episode_steps=50, terminate_on_success=True, seed=0,
                 render_size=None, **options):
        if options:
            raise ValueError(f"{self.label} has no cameras, state options or perturbations, got {sorted(options)}")
        return ReacherChunkEnv(n_exec, max_episode_steps, terminate_on_success, seed, render_size)

    def expert(self, task: str, seed: int) -> Expert:
        return ReacherExpert(seed)
