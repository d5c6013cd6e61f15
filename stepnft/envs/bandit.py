"""A contextual bandit with binary success, for unit tests and the core demo (not a benchmark).

The context ``c ~ U[-1, 1]^2`` sets a target action ``g(c)``; an episode is ``horizon`` env
steps under that context and succeeds when every action lies within ``radius`` of the target.
A policy with chunks of ``horizon`` actions plays an episode in one call. Demonstrations come
from a biased, noisy expert, so behaviour cloning succeeds only part of the time and RL has
room to improve. It implements the same simulator interface as MetaWorld, so the whole
training loop (collector, algorithms, evaluation, checkpoints) runs on it in seconds.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding

from stepnft.envs.base import Expert, Simulator, checked_chunk

CONTEXT_DIM = 2
ACTION_DIM = 2
HORIZON = 2
RADIUS = 0.15
DEMO_BIAS = 0.12
DEMO_NOISE = 0.08


def target(context: np.ndarray) -> np.ndarray:
    """The context-dependent centre of the success region ``[..., 2]``."""
    c0, c1 = context[..., 0], context[..., 1]
    return 0.6 * np.stack([np.sin(math.pi * c0), c0 * c1], axis=-1)


class BanditChunkEnv(gym.Env):
    """Observation ``{"state": context [2]}``; action ``[n_exec, 2]``; ``HORIZON`` steps per episode."""

    def __init__(self, n_exec: int = HORIZON, max_episode_steps: int = HORIZON, terminate_on_success: bool = True,
                 seed: int = 0):
        if n_exec < 1:
            raise ValueError(f"n_exec must be >= 1, got {n_exec}")
        self.n_exec, self.max_episode_steps = n_exec, max_episode_steps
        self.observation_space = gym.spaces.Dict({"state": gym.spaces.Box(-1.0, 1.0, (CONTEXT_DIM,), np.float32)})
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n_exec, ACTION_DIM), np.float32)
        self.np_random, _ = seeding.np_random(seed)
        self._context: np.ndarray | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if options and options.get("idle"):  # sit a batch step out (see stepnft.envs.base)
            if self._context is None:
                self._context = np.zeros(CONTEXT_DIM, dtype=np.float32)
            self._steps, self._all_within, self._success, self._done = 0, False, False, True
            return {"state": self._context.copy()}, self._info(0)
        super().reset(seed=seed)
        self._context = self.np_random.uniform(-1.0, 1.0, CONTEXT_DIM).astype(np.float32)
        self._steps, self._all_within, self._success, self._done = 0, True, False, False
        return {"state": self._context.copy()}, self._info(0)

    def step(self, chunk: np.ndarray):
        chunk = checked_chunk(chunk, self.action_space, self._context is not None)
        obs = {"state": self._context.copy()}
        if self._done:
            return obs, 0.0, self._success, not self._success, self._info(0)
        steps = 0
        goal = target(self._context.astype(np.float64))
        for action in np.clip(chunk, -1.0, 1.0):
            steps += 1
            self._steps += 1
            self._all_within &= bool(np.linalg.norm(action - goal) < RADIUS)
            if self._steps >= HORIZON or self._steps >= self.max_episode_steps:
                self._done = True
                self._success = self._all_within and self._steps >= HORIZON
                break
        reward = float(self._success)
        return obs, reward, self._done and self._success, self._done and not self._success, self._info(steps)

    def _info(self, steps: int) -> dict[str, Any]:
        return {"success": self._success, "steps": steps, "episode_steps": self._steps}


class _BiasedExpert(Expert):
    def __init__(self, seed: int):
        self._rng = np.random.default_rng(seed)

    def act(self, obs):
        offset = np.array([DEMO_BIAS, -DEMO_BIAS]) / math.sqrt(2)
        return target(obs["state"].astype(np.float64)) + offset + DEMO_NOISE * self._rng.standard_normal(ACTION_DIM)


class Bandit(Simulator):
    name = "bandit"
    label = "bandit"
    state_dim = CONTEXT_DIM
    action_dim = ACTION_DIM
    control_hz = 1.0

    def task_names(self) -> list[str]:
        return ["bandit"]

    def instruction(self, task: str) -> str:
        return "put every action of the chunk on the target"

    def make_env(self, task, n_exec=HORIZON, max_episode_steps=HORIZON, terminate_on_success=True, seed=0,
                 render_size=None, **options):
        if render_size is not None or options:
            raise ValueError("the bandit has nothing to render and no cameras, state options or perturbations")
        return BanditChunkEnv(n_exec=n_exec, max_episode_steps=max_episode_steps, seed=seed)

    def expert(self, task: str, seed: int) -> Expert:
        return _BiasedExpert(seed)
