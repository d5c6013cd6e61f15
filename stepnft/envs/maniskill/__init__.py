"""ManiSkill3 (SAPIEN) behind stepnft's environment interface: 12 tabletop tasks with a Panda
arm that need no asset downloads, 64-d privileged state, 7-d end-effector actions, cameras,
success from ManiSkill's ``info["success"]``, scripted experts for PickCube-v1, PushCube-v1,
PullCube-v1 and StackCube-v1 (docs/maniskill.md).

An optional extra: ``pip install "stepnft[maniskill]"`` (mani-skill 3.0.1, sapien 3.0.3), and a
Vulkan driver (``bash scripts/bootstrap.sh --maniskill`` installs both).
"""

from __future__ import annotations

import logging
import os

os.environ.setdefault("LP_NUM_THREADS", "1")  # one lavapipe thread per process: workers render side by side
try:
    import mani_skill  # noqa: F401
    import sapien  # noqa: F401
except ImportError as err:
    raise ImportError(f"ManiSkill is not installed ({err}): pip install 'stepnft[maniskill]' or "
                      "bash scripts/bootstrap.sh --maniskill (docs/maniskill.md)") from err

from stepnft.envs.base import Expert, Simulator
from stepnft.envs.maniskill.env import ACTION_DIM, CONTROL_HZ, ManiSkillChunkEnv
from stepnft.envs.maniskill.experts import EXPERTS
from stepnft.envs.maniskill.tasks import STATE_DIM, TASKS

__all__ = ["ManiSkill", "ManiSkillChunkEnv", "TASKS", "EXPERTS"]

# ManiSkill warns on every env it builds (actors without an initial pose, ...): not the user's concern.
logging.getLogger("mani_skill ").setLevel(logging.ERROR)  # sic: its logger's name ends with a space


class ManiSkill(Simulator):
    """ManiSkill3's asset-free tabletop tasks (``tasks.TASKS``). Cameras: ``base_camera`` (every
    task) and ``hand_camera`` (StackCube, PegInsertionSide, PlugCharger, StackPyramid)."""

    name = "maniskill"
    label = "ManiSkill"
    distribution = "mani-skill"
    state_dim = STATE_DIM
    action_dim = ACTION_DIM
    control_hz = float(CONTROL_HZ)

    def task_names(self) -> list[str]:
        return list(TASKS)

    def instruction(self, task: str) -> str:
        return TASKS[task].instruction

    def make_env(self, task, n_exec=1, max_episode_steps=200, terminate_on_success=True, seed=0, render_size=None,
                 **options):
        return ManiSkillChunkEnv(task, n_exec=n_exec, max_episode_steps=max_episode_steps,
                                 terminate_on_success=terminate_on_success, seed=seed, render_size=render_size, **options)

    def make_vec_env(self, tasks, envs_per_task=1, n_exec=4, max_episode_steps=200, terminate_on_success=True, seed=0,
                     num_workers=0, sub_envs=None, sim_backend="cpu", **options):
        """As :meth:`Simulator.make_vec_env`; ``sim_backend="gpu"``: each task's sub-envs are the
        scenes of one batched ManiSkill env on the GPU's physics (``stepnft.envs.maniskill.gpu``)."""
        if sim_backend == "cpu":
            return super().make_vec_env(tasks, envs_per_task, n_exec, max_episode_steps, terminate_on_success, seed,
                                        num_workers, sub_envs, **options)
        if sim_backend != "gpu":
            raise ValueError(f"sim_backend must be cpu or gpu, got {sim_backend!r}")
        if num_workers or sub_envs is not None:
            raise ValueError("env.sim_backend gpu steps every scene in this process's batched env: use env.num_workers 0 "
                             "and no Ray workers")
        extra = set(options) - {"cameras", "image_size"}
        if extra:
            raise ValueError(f"env.sim_backend gpu does not take {', '.join(sorted(extra))}")
        import torch

        if not torch.cuda.is_available():
            raise ValueError("env.sim_backend gpu needs CUDA (ManiSkill's GPU physics), which this machine lacks; "
                             "use env.sim_backend cpu")
        from stepnft.envs.maniskill.gpu import ManiSkillGPUVecEnv

        layout = self.vec_env_layout(tasks, envs_per_task)
        return ManiSkillGPUVecEnv(layout["tasks"], layout["instructions"], layout["task_ids"],
                                  layout["instruction_variants"], n_exec=n_exec, max_episode_steps=max_episode_steps,
                                  terminate_on_success=terminate_on_success, seed=seed, **options)

    def expert(self, task: str, seed: int) -> Expert:
        (task,) = self.validate_tasks([task])
        if task not in EXPERTS:
            raise ValueError(f"ManiSkill has scripted experts for {', '.join(EXPERTS)} only, not {task}")
        return EXPERTS[task]()  # deterministic: the seed is not needed
