"""LIBERO's task suites: their tasks, instructions, fixed initial states and episode caps.

Read from the installed LIBERO package (``libero.libero.benchmark``, no simulator import): a
suite lists ten tasks (libero_90: ninety) in LIBERO's own order (task order 0), each with a BDDL
task definition, a language instruction and 50 fixed initial simulator states.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
from dataclasses import dataclass
from functools import cache

import numpy as np

SUITE_MAX_STEPS = {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520,
                   "libero_90": 400}
"""Episode caps in env steps of the reference evaluation (OpenVLA's LIBERO evaluation, also
LeRobot's): a little longer than each suite's longest training demonstration (193, 254, 270,
505 and 373 steps), not counting the settling steps after a reset."""

SUITES = tuple(SUITE_MAX_STEPS)
"""The four benchmark suites (libero_10 is LIBERO-Long) and libero_90."""


@dataclass(frozen=True)
class LiberoTask:
    name: str
    """LIBERO's task name (its BDDL file name without ``.bddl``)."""
    suite: str
    index: int
    """Position in the suite (LIBERO's task id)."""
    instruction: str
    """The task's language instruction in LIBERO's benchmark (what policies are evaluated with;
    the BDDL file's own ``:language`` line words 29 of the 130 tasks differently)."""
    bddl_file: str
    """Path of the BDDL task definition."""

    @property
    def max_episode_steps(self) -> int:
        return SUITE_MAX_STEPS[self.suite]

    def bddl_instruction(self) -> str:
        """The ``:language`` line of the BDDL definition (LIBERO's HDF5 files carry this one)."""
        with open(self.bddl_file) as f:
            match = re.search(r"\(:language\s+([^)]*)\)", f.read())
        return match.group(1).strip() if match else self.instruction


@cache
def _suite_objects() -> dict:
    from libero.libero import benchmark

    with contextlib.redirect_stdout(io.StringIO()):  # LIBERO prints the task order of each suite
        return {name: benchmark.get_benchmark_dict()[name]() for name in SUITES}


@cache
def all_tasks() -> dict[str, LiberoTask]:
    """Every task of the suites by name, suite by suite in LIBERO's order."""
    from libero.libero import get_libero_path

    tasks = {}
    for suite_name, suite in _suite_objects().items():
        for i in range(suite.get_num_tasks()):
            task = suite.get_task(i)
            bddl = os.path.join(get_libero_path("bddl_files"), task.problem_folder, task.bddl_file)
            tasks[task.name] = LiberoTask(task.name, suite_name, i, task.language, bddl)
    return tasks


def suite_tasks(suite: str) -> list[str]:
    """The task names of ``suite`` in LIBERO's order."""
    return [t.name for t in all_tasks().values() if t.suite == suite]


def initial_states(task: str) -> np.ndarray:
    """The task's fixed initial simulator states, float64 [50, D] (flattened MuJoCo states)."""
    info = all_tasks()[task]
    return np.asarray(_suite_objects()[info.suite].get_task_init_states(info.index), dtype=np.float64)
