"""Which code made a file: the package version and, in a git checkout, its commit. Recorded in
what outlives a run (a demonstrations folder's manifest), so that reusing it with other code can
say so."""

from __future__ import annotations

import subprocess
from pathlib import Path

import stepnft

CHECKOUT = Path(stepnft.__file__).resolve().parents[1]


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(CHECKOUT), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def code_commit() -> str | None:
    """The short commit of the checkout this package is imported from, with ``+uncommitted`` when
    ``stepnft/`` differs from it; None outside a git checkout (an installed wheel)."""
    if not (CHECKOUT / "stepnft").is_dir():
        return None
    head = _git("rev-parse", "--short=12", "HEAD")  # None outside a git checkout
    if not head:
        return None
    return head + ("+uncommitted" if _git("status", "--porcelain", "--", "stepnft") else "")


def code_version() -> dict:
    """``{"stepnft": version, "commit": code_commit()}``."""
    return {"stepnft": stepnft.__version__, "commit": code_commit()}


def changed_since(commit: str | None, paths: tuple[str, ...]) -> list[str] | None:
    """The files under ``paths`` (relative to the checkout) that differ between ``commit`` and the
    code running now (committed or not); None when that cannot be told (no commit recorded, or one
    with uncommitted changes; not a git checkout; a commit this checkout does not have)."""
    if not commit or "+" in commit or code_commit() is None:
        return None
    names = _git("diff", "--name-only", commit, "--", *paths)
    return None if names is None else names.splitlines()
