"""Deterministic evaluation: ODE sampling on a fixed, seeded set of initial states.

Episode ``e`` of every task starts from initial state ``seed + e``, whatever the checkpoint or
algorithm, so figures from different runs are paired. Success rates come with a Wilson 95 %
confidence interval.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from stepnft.policies.flow import FlowPolicy
from stepnft.rollout.collector import run_wave


def wilson_interval(successes: int, episodes: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (95 % for ``z = 1.96``)."""
    if episodes == 0:
        return 0.0, 1.0
    p = successes / episodes
    denom = 1 + z**2 / episodes
    centre = (p + z**2 / (2 * episodes)) / denom
    half = z * math.sqrt(p * (1 - p) / episodes + z**2 / (4 * episodes**2)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def evaluate_policy(
    policy: FlowPolicy,
    venv,
    lang_table: Tensor | None,
    episodes: int,
    seed: int = 0,
    progress=None,
) -> dict:
    """Success per task over ``episodes`` episodes each, ODE sampling.

    ``venv`` has ``envs_per_task`` sub-envs per task (autoreset disabled); each wave plays
    ``envs_per_task`` new episodes of every task. Returns ``{"tasks": {task: {...}},
    "average": rate, "episodes": per task, "env_steps": total}``.
    """
    policy.eval()
    task_ids = np.asarray(venv.task_ids)
    n_tasks = len(venv.tasks)
    per_task = len(task_ids) // n_tasks
    slot = np.zeros_like(task_ids)
    for k in range(n_tasks):
        slot[task_ids == k] = np.arange(per_task)
    successes = np.zeros(n_tasks, dtype=np.int64)
    counts = np.zeros(n_tasks, dtype=np.int64)
    env_steps = 0
    waves = math.ceil(episodes / per_task)
    for w in range(waves):
        episode = w * per_task + slot
        wave = run_wave(
            policy, venv, lang_table, noise_level=0.0,
            generator=torch.Generator().manual_seed(seed * 100_003 + w),
            seeds=[int(seed + e) for e in episode],
        )
        valid = episode < episodes
        np.add.at(successes, task_ids[valid], wave.success[valid])
        np.add.at(counts, task_ids[valid], 1)
        env_steps += int(wave.length.sum())
        if progress is not None:
            progress(w + 1, waves)
    tasks = {}
    for k, name in enumerate(venv.tasks):
        lo, hi = wilson_interval(int(successes[k]), int(counts[k]))
        tasks[name] = {"success": successes[k] / counts[k], "successes": int(successes[k]),
                       "episodes": int(counts[k]), "ci95": [lo, hi]}
    return {"tasks": tasks, "average": float(np.mean([v["success"] for v in tasks.values()])),
            "episodes": episodes, "env_steps": env_steps}


def format_table(before: dict | None, after: dict) -> str:
    """A plain-text table: task, success before -> after with 95 % CIs."""
    lines = [f"{'task':<18} {'before':>22} {'after':>22}"]
    for task, res in after["tasks"].items():
        b = before["tasks"][task] if before else None
        cell = lambda r: f"{r['success']:.2f} [{r['ci95'][0]:.2f},{r['ci95'][1]:.2f}]" if r else "-"  # noqa: E731
        lines.append(f"{task:<18} {cell(b):>22} {cell(res):>22}")
    avg_b = f"{before['average']:.3f}" if before else "-"
    lines.append(f"{'average':<18} {avg_b:>22} {after['average']:>22.3f}")
    return "\n".join(lines)
