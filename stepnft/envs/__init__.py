"""Simulator adapters. Kept import-light: the CLI reads DEFAULT_TASKS without loading MuJoCo."""

DEFAULT_TASKS = ["reach-v3", "push-v3", "pick-place-v3", "door-open-v3", "drawer-open-v3"]
"""The embedded default: five MetaWorld v3 tasks, one multi-task policy."""
