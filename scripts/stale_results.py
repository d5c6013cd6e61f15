"""List the result folders under benchmarks/results/ that were made on code older than the
package code they depend on (``stepnft/`` and ``configs/``).

A folder's commit is the ``commit`` its JSON files record (benchmarks write it), else the commit
that last added or changed the folder in git (the results were made on the code before it).
A folder is *stale* when ``stepnft/`` or ``configs/`` changed after that commit: its figures may
no longer be what the code gives (a change that keeps every number, e.g. a refactor checked
bit for bit, still counts unless it is listed in ``benchmarks/results/neutral_commits.txt``:
one commit per line, then how it was shown to change no figure, e.g. a run's metrics and weights
compared bit for bit before and after; ``except:a,b`` after the commit names folders it still
counts for). A commit that changes only files under ``configs/``
counts for a folder only if a command the folder records (``command`` in its JSON files) names
one of those files, or one of its commands names no ``--config`` (the default config may be one
of them). Exit code 0; with ``--fail`` 1 when any folder is stale.

The same code gives other numbers on other versions of numpy, scipy, MuJoCo, ... (docs/experiments.md
§14), so each folder also gets an *environment* column: ``pinned`` when the ``packages`` its JSON
files record (benchmarks/provenance.py) are the versions constraints.txt pins, ``differs`` (which)
otherwise (also when a run records torch's AVX-512 kernels, ``cpu`` in its JSON), ``unrecorded`` when it records none (made before the pins: the figures may not come
back on a pinned checkout even where the code is current). This column does not make a folder stale.

    python scripts/stale_results.py            # every folder, stale ones first
    python scripts/stale_results.py --fail     # for CI-style checks
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEPENDS_ON = ("stepnft", "configs")
NEUTRAL = Path("benchmarks/results/neutral_commits.txt")


def git(root: Path, *args: str) -> str:
    return subprocess.run(["git", *args], capture_output=True, text=True, cwd=root, check=False).stdout.strip()


def recorded(folder: Path, key: str, kind: type = str) -> list:
    """The non-empty values of type ``kind`` a benchmark wrote under ``key`` into the folder's JSON files."""
    values = []
    for path in sorted(folder.glob("*.json")):
        try:
            value = json.loads(path.read_text()).get(key)
        except (ValueError, AttributeError, OSError):
            continue
        if isinstance(value, kind) and value:
            values.append(value)
    return values


def recorded_packages(folder: Path) -> dict[str, str] | None:
    """The ``packages`` (name -> version) a benchmark wrote into one of the folder's JSON files."""
    found = recorded(folder, "packages", dict)
    return found[0] if found else None


def pinned_versions(root: Path) -> dict[str, str]:
    """``name==version`` lines of the checkout's constraints.txt, by lower-case name."""
    path = root / "constraints.txt"
    lines = path.read_text().splitlines() if path.is_file() else []
    return {name.strip().lower(): version.strip() for name, _, version in
            (line.split("#")[0].partition("==") for line in lines) if version.strip()}


def recorded_kernels(folder: Path) -> set[str]:
    """The ATen dispatch levels (``AVX2``, ``AVX512``, ...) the folder's JSON files record, for the
    whole file (``cpu``) or per run (``runs[i].cpu``, benchmarks/learning.py)."""
    levels = set()
    for path in sorted(folder.glob("*.json")):
        try:
            data = json.loads(path.read_text())
        except (ValueError, OSError):
            continue
        if not isinstance(data, dict):
            continue
        runs = data.get("runs") if isinstance(data.get("runs"), list) else []
        for cpu in [data.get("cpu")] + [r.get("cpu") for r in runs if isinstance(r, dict)]:
            if isinstance(cpu, dict) and cpu.get("aten_capability"):
                levels.add(cpu["aten_capability"])
    return levels


def environment(root: Path, folder: Path) -> str:
    """``pinned``, ``unrecorded`` or ``differs: name have!=pin, ...`` (local tags like +cpu ignored;
    ``ATen AVX512`` when a run computed with torch's AVX-512 kernels, which give other numbers)."""
    packages = recorded_packages(folder)
    if packages is None:
        return "unrecorded"
    pins = pinned_versions(root)
    off = [f"{name} {version}!={pins[name.lower()]}" for name, version in sorted(packages.items())
           if version and name.lower() in pins and version.split("+")[0] != pins[name.lower()]]
    off += ["ATen AVX512"] if "AVX512" in recorded_kernels(folder) else []
    return "differs: " + ", ".join(off) if off else "pinned"


def recorded_commit(folder: Path) -> str | None:
    """The ``commit`` a benchmark wrote into one of the folder's JSON files (without a
    ``+uncommitted`` suffix), if any."""
    commits = recorded(folder, "commit")
    return commits[0].split("+")[0] if commits else None


def recorded_commands(folder: Path) -> list[str]:
    """The ``command`` strings a benchmark wrote into the folder's JSON files."""
    return recorded(folder, "command")


def reads_configs(commands: list[str], changed: list[str]) -> bool:
    """Whether runs of ``commands`` may read one of the ``changed`` config files: each command
    must name its ``--config`` and none may be among them (no recorded command: assume yes)."""
    if not commands or any("--config" not in c.split() for c in commands):
        return True
    return any(path in c.split() for c in commands for path in changed)


def folder_commit(root: Path, folder: Path) -> tuple[str | None, bool]:
    """``(commit, recorded)``: the recorded commit, or the one that last committed the folder."""
    recorded = recorded_commit(folder)
    if recorded:
        return recorded, True
    return git(root, "log", "-1", "--format=%h", "--", str(folder.relative_to(root))) or None, False


def neutral_commits(root: Path, folder: str | None = None) -> list[str]:
    """The commits listed as changing no figure (first word of each line; ``#`` comments); a
    line may name folders it does not hold for, ``except:name,name`` as its second word (e.g. a
    change that keeps every MetaWorld figure but moves the LIBERO ones)."""
    path = root / NEUTRAL
    lines = path.read_text().splitlines() if path.is_file() else []
    neutral = []
    for line in lines:
        words = line.split()
        if not words or line.lstrip().startswith("#"):
            continue
        if len(words) > 1 and words[1].startswith("except:") and folder in words[1][7:].split(","):
            continue
        neutral.append(words[0])
    return neutral


def changes_since(root: Path, commit: str, recorded: bool, commands: list[str] | None = None,
                  folder: str | None = None) -> list[str]:
    """Commits that changed the code the results depend on since they were made: after a
    recorded commit, or since the parent of the commit that committed them (its own code
    changes count: the results were made before it); those listed as neutral do not count, nor
    those changing only config files the folder's ``commands`` do not read."""
    if not git(root, "rev-parse", "--verify", "--quiet", f"{commit}^{{commit}}"):
        return ["(unknown commit)"]
    base = commit if recorded else f"{commit}~1"
    span = ["HEAD"] if not recorded and not git(root, "rev-parse", "--verify", "--quiet", base) else [f"{base}..HEAD"]
    log = git(root, "log", "--format=%H %h %ad %s", "--date=short", *span, "--", *DEPENDS_ON).splitlines()
    neutral = neutral_commits(root, folder)
    counted = []
    for line in log:
        if any(line.startswith(n) for n in neutral):
            continue
        files = git(root, "show", "--format=", "--name-only", line.split()[0], "--", *DEPENDS_ON).splitlines()
        if files and all(f.startswith("configs/") for f in files) and not reads_configs(commands or [], files):
            continue
        counted.append(line.split(" ", 1)[1])
    return counted


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", default=str(ROOT), help="the checkout (default: this script's)")
    p.add_argument("--fail", action="store_true", help="exit 1 when a folder is stale")
    args = p.parse_args(argv)
    root = Path(args.root).resolve()
    rows = []
    for folder in sorted(f for f in (root / "benchmarks" / "results").iterdir() if f.is_dir()):
        commit, recorded = folder_commit(root, folder)
        env = environment(root, folder)
        if commit is None:
            rows.append((True, folder.name, "not committed", [], env))
            continue
        changes = changes_since(root, commit, recorded, recorded_commands(folder), folder.name)
        rows.append((bool(changes), folder.name, f"{'recorded' if recorded else 'committed in'} {commit}", changes, env))
    print(f"{'folder':<32} {'made on':<22} {'code':<40} environment")
    for stale, name, where, changes, env in sorted(rows, key=lambda r: (not r[0], r[1])):
        state = f"STALE ({len(changes)} code commits since)" if stale else "current"
        print(f"{name:<32} {where:<22} {state:<40} {env}")
        if stale and changes:
            print(f"{'':<32} latest: {changes[0][:100]}")
    return 1 if args.fail and any(r[0] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
