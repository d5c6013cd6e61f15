"""``python -m stepnft.envs.libero``: the suites, their tasks, instructions and episode caps."""

from stepnft.envs.libero import SUITE_MAX_STEPS, SUITES
from stepnft.envs.libero.suites import all_tasks

for suite in SUITES:
    print(f"{suite} (episode cap {SUITE_MAX_STEPS[suite]} steps)")
    for task in all_tasks().values():
        if task.suite == suite:
            print(f"  {task.index:2d}  {task.name}\n      \"{task.instruction}\"")
