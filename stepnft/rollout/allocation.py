"""Where rollouts go: how many of an iteration's episodes each task plays.

``equal`` gives every task the same share. ``informative``
gives more episodes to the tasks that can teach most: a task whose episodes all succeed or all
fail yields (almost) no contrast between successes and failures, while one near 50 % yields the
most. Each task's share is ``floor / T + (1 - floor) * w_t / sum(w)`` with
``w_t = p_t (1 - p_t)`` (the variance of its success), where ``p_t`` is a running estimate of
the task's rollout success; the floor keeps every task in play, so a task at 0 or 1 is still
watched and can come back.
"""

from __future__ import annotations

import numpy as np

from stepnft.batch import Batch


class TaskAllocator:
    """Running per-task success estimates and the episodes each task gets next iteration."""

    def __init__(self, num_tasks: int, mode: str = "equal", floor: float = 0.3, smoothing: float = 0.5,
                 initial_success: list[float] | None = None):
        if mode not in ("equal", "informative"):
            raise ValueError(f"task allocation must be 'equal' or 'informative', got {mode!r}")
        self.mode, self.floor, self.smoothing = mode, floor, smoothing
        self.success = np.full(num_tasks, 0.5) if initial_success is None else np.asarray(initial_success, float)

    def update(self, batch: Batch) -> None:
        """Fold an iteration's rollout outcomes into the estimates (tasks it did not play keep theirs)."""
        for k in range(len(self.success)):
            played = batch.episode_success[batch.episode_task == k]
            if len(played):
                rate = float(played.double().mean())
                self.success[k] = self.smoothing * self.success[k] + (1 - self.smoothing) * rate

    def shares(self) -> np.ndarray:
        """Fraction of the next iteration's episodes per task (sums to 1)."""
        n = len(self.success)
        if self.mode == "equal":
            return np.full(n, 1.0 / n)
        w = self.success * (1 - self.success)
        spread = w / w.sum() if w.sum() > 0 else np.full(n, 1.0 / n)
        return self.floor / n + (1 - self.floor) * spread

    def allocate(self, episodes: int, multiple: int = 1) -> list[int] | None:
        """Episodes per task for the next iteration (None: ``equal``, the collector splits them
        evenly), each a multiple of ``multiple`` (a GRPO group) and at least one group."""
        if self.mode == "equal":
            return None
        groups = max(len(self.success), int(np.ceil(episodes / multiple)))
        raw = self.shares() * groups
        counts = np.maximum(np.floor(raw).astype(int), 1)
        while counts.sum() < groups:  # largest remainders first
            counts[np.argmax(raw - counts)] += 1
        return [int(c) * multiple for c in counts]

    def state_dict(self) -> dict:
        return {"success": self.success.tolist()}

    def load_state_dict(self, state: dict) -> None:
        self.success = np.asarray(state["success"], dtype=float)
