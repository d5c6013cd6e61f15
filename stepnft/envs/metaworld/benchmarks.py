"""MetaWorld's multi-task benchmarks (MT10, MT50) and the difficulty splits results are reported by.

MT10 is MetaWorld's own list (``metaworld.env_dict.MT10_V3``); MT50 is every v3 task. The splits
(easy 28, medium 11, hard 6, very hard 5 tasks) are the ones Seo et al. (2022, "Masked World
Models") defined from how fast a reference agent learns each task, and the ones RLinf and LeRobot
report MetaWorld per difficulty with. This module does not import MetaWorld;
``tests/envs/test_metaworld.py`` checks the lists against it.
"""

from __future__ import annotations

MT10: tuple[str, ...] = ("reach-v3", "push-v3", "pick-place-v3", "door-open-v3", "drawer-open-v3", "drawer-close-v3",
                         "button-press-topdown-v3", "peg-insert-side-v3", "window-open-v3", "window-close-v3")
"""MetaWorld's MT10, in its own order."""

MEDIUM = ("basketball-v3", "bin-picking-v3", "box-close-v3", "coffee-pull-v3", "coffee-push-v3", "hammer-v3",
          "peg-insert-side-v3", "push-wall-v3", "soccer-v3", "sweep-v3", "sweep-into-v3")
HARD = ("assembly-v3", "hand-insert-v3", "pick-out-of-hole-v3", "pick-place-v3", "push-v3", "push-back-v3")
VERY_HARD = ("shelf-place-v3", "disassemble-v3", "stick-pull-v3", "stick-push-v3", "pick-place-wall-v3")


def _mt50() -> tuple[str, ...]:
    from stepnft.envs.metaworld.instructions import INSTRUCTIONS  # one instruction per v3 task: all 50

    return tuple(sorted(INSTRUCTIONS))


MT50: tuple[str, ...] = _mt50()
"""Every MetaWorld v3 task, sorted by name."""

EASY = tuple(t for t in MT50 if t not in MEDIUM + HARD + VERY_HARD)

DIFFICULTY: dict[str, tuple[str, ...]] = {"easy": EASY, "medium": MEDIUM, "hard": HARD, "very_hard": VERY_HARD}
"""The difficulty splits, each a tuple of task names; together they are MT50, each task once."""


def difficulty_of(task: str) -> str:
    """The split (``easy``, ``medium``, ``hard``, ``very_hard``) of a MetaWorld v3 task."""
    for split, tasks in DIFFICULTY.items():
        if task in tasks:
            return split
    raise KeyError(f"{task!r} is not a MetaWorld v3 task")
