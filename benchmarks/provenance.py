"""What a results folder records about how it was made: the exact command, the commit it ran on
(``scripts/stale_results.py`` reads the commit), the versions of the packages its numbers
depend on (the same code gave another SFT start with other versions, before constraints.txt pinned them)
and the CPU kernels torch used (ATen's AVX-512 kernels moved the main command's RL run,
docs/experiments.md §14)."""

from __future__ import annotations

import os
import platform
import shlex
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
    """The command line that is running, with the interpreter relative to the checkout, quoted as
    a shell reads it (an argument with spaces stays one argument)."""
    return shlex.join([os.path.relpath(sys.executable, ROOT), *sys.argv])


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


def cpu() -> dict[str, str | None]:
    """The CPU model and the instruction sets torch computed with in this process: ATen's
    dispatch level (``AVX2`` under stepnft's cap, ``AVX512`` if torch ran an op before stepnft
    was imported or the cap was lifted) and oneDNN's cap. Call it after importing stepnft."""
    import torch

    model = None
    try:
        model = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                      if line.startswith("model name")), None)
    except OSError:  # not Linux
        pass
    return {"model": model or platform.processor() or None, "aten_capability": torch.backends.cpu.get_cpu_capability(),
            "onednn_max_cpu_isa": os.environ.get("ONEDNN_MAX_CPU_ISA")}


def write_results(out: Path, stem: str, record: dict, text: str, header: str) -> None:
    """``OUT/STEM.json`` (the record) and ``OUT/STEM.md`` (``header``, then ``text``, the table the
    script prints), the folder made if needed."""
    import json

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(record, indent=2))
    (out / f"{stem}.md").write_text(f"{header}\n\n{text}\n")
