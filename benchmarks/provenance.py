"""What a results folder records about how it was made: the exact command, the commit it ran on
(``scripts/stale_results.py`` reads the commit) and the versions of the packages its numbers
depend on (the same code gave another SFT start with other versions, before constraints.txt pinned them)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def commit() -> str:
    """The checkout's short commit, ``+uncommitted`` if the package, configs or benchmarks differ from it."""
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "stepnft", "configs", "benchmarks/*.py"], capture_output=True,
                           text=True, cwd=ROOT).stdout.strip()
    return head + ("+uncommitted" if dirty else "")


def command() -> str:
    """The command line that is running, with the interpreter relative to the checkout."""
    return " ".join([os.path.relpath(sys.executable, ROOT), *sys.argv])


NUMERIC_PACKAGES = ("torch", "numpy", "scipy", "mujoco", "metaworld", "gymnasium")
"""The packages whose versions move a run's numbers (physics, sampling, optimisation)."""


def packages(names: tuple[str, ...] = NUMERIC_PACKAGES) -> dict[str, str | None]:
    """The installed version of each of ``names`` (None where absent); a simulator's benchmark adds
    its own packages (e.g. mani-skill, sapien) to :data:`NUMERIC_PACKAGES`."""
    from importlib.metadata import PackageNotFoundError, version

    found = {}
    for name in names:
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            found[name] = None
    return found
