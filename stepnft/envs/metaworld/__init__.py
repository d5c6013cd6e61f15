"""MetaWorld v3 (MuJoCo) behind stepnft's environment interface: 50 tasks, 39-dim state,
4-dim actions, scripted experts for demonstrations."""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

from stepnft.envs.base import Expert, Simulator
from stepnft.envs.metaworld.env import (
    ACTION_DIM,
    MAX_PATH_LENGTH,
    OBS_DIM,
    SIM_STEPS_PER_SECOND,
    STATE_OBS,
    TASK_NAMES,
    MetaWorldChunkEnv,
)
from stepnft.envs.metaworld.instructions import INSTRUCTIONS, instruction_for, task_instruction_variants
from stepnft.envs.perturbations import Perturbations

__all__ = ["MetaWorld", "MetaWorldChunkEnv", "make_metaworld_vec_env", "validate_tasks", "TASK_NAMES", "OBS_DIM",
           "ACTION_DIM", "MAX_PATH_LENGTH", "SIM_STEPS_PER_SECOND", "INSTRUCTIONS", "instruction_for"]


class _ScriptedExpert(Expert):
    """MetaWorld's own scripted policy for one task (``metaworld.policies.ENV_POLICY_MAP``)."""

    def __init__(self, task: str):
        from metaworld.policies import ENV_POLICY_MAP

        self._policy = ENV_POLICY_MAP[task]()

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        with warnings.catch_warnings():
            # The experts warn when their gains saturate an action; it is clipped anyway.
            warnings.filterwarnings("ignore", "Constant", UserWarning)
            return self._policy.get_action(obs["state"])


class MetaWorld(Simulator):
    name = "metaworld"
    label = "MetaWorld"
    state_dim = OBS_DIM
    action_dim = ACTION_DIM
    control_hz = SIM_STEPS_PER_SECOND

    def task_names(self) -> list[str]:
        return list(TASK_NAMES)

    def instruction(self, task: str) -> str:
        return instruction_for(task)

    def make_env(self, task, n_exec=1, max_episode_steps=200, terminate_on_success=True, seed=0, render_size=None,
                 **options):
        return MetaWorldChunkEnv(task, n_exec=n_exec, max_episode_steps=max_episode_steps,
                                 terminate_on_success=terminate_on_success, seed=seed, render_size=render_size, **options)

    def state_dim_for(self, state_obs: str = "full") -> int:
        if state_obs not in STATE_OBS:
            raise ValueError(f"MetaWorld's state_obs is one of {', '.join(STATE_OBS)}, got {state_obs!r}")
        return STATE_OBS[state_obs]

    def instruction_variants(self, task: str, perturbations: Perturbations | None = None) -> list[str]:
        return task_instruction_variants(task, perturbations or Perturbations())[0]

    def expert(self, task: str, seed: int) -> Expert:
        (task,) = self.validate_tasks([task])
        return _ScriptedExpert(task)  # deterministic: the seed is not needed


def validate_tasks(tasks: str | Sequence[str]) -> list[str]:
    """Checks MetaWorld v3 task names; `tasks` is a list or a comma-separated string."""
    return MetaWorld().validate_tasks(tasks)


def make_metaworld_vec_env(tasks, envs_per_task: int = 1, n_exec: int = 4, max_episode_steps: int = 200,
                           terminate_on_success: bool = True, seed: int = 0, num_workers: int = 0, **options):
    """A batch of ``len(tasks) * envs_per_task`` MetaWorld chunk envs (autoreset disabled);
    see :meth:`stepnft.envs.base.Simulator.make_vec_env`."""
    return MetaWorld().make_vec_env(tasks, envs_per_task, n_exec, max_episode_steps, terminate_on_success, seed,
                                    num_workers, **options)
