"""scripts/stale_results.py on a throwaway git checkout: a results folder is stale once the
package code changed after the commit it ran on (recorded, or the one that committed it)."""

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "stale_results.py"


def git(root: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=root, check=True,
                          capture_output=True, text=True).stdout.strip()


def stale(root: Path) -> dict[str, bool]:
    out = subprocess.run([sys.executable, str(SCRIPT), "--root", str(root)], capture_output=True, text=True, check=True)
    return {line.split()[0]: "STALE" in line for line in out.stdout.splitlines()[1:] if not line.startswith(" ")}


def environments(root: Path) -> dict[str, str]:
    out = subprocess.run([sys.executable, str(SCRIPT), "--root", str(root)], capture_output=True, text=True, check=True)
    header, *rows = out.stdout.splitlines()
    column = header.index("environment")
    return {line.split()[0]: line[column:].strip() for line in rows if not line.startswith(" ")}


def test_folders_older_than_the_code_are_listed_as_stale(tmp_path):
    git(tmp_path, "init", "-q")
    (tmp_path / "stepnft").mkdir()
    (tmp_path / "stepnft" / "core.py").write_text("x = 1\n")
    results = tmp_path / "benchmarks" / "results"
    for name in ("old", "new", "recorded"):
        (results / name).mkdir(parents=True)
        (results / name / "table.md").write_text(name)
    git(tmp_path, "add", "-A")
    git(tmp_path, "commit", "-qm", "code and results")
    first = git(tmp_path, "rev-parse", "--short", "HEAD")
    (tmp_path / "stepnft" / "core.py").write_text("x = 2\n")
    git(tmp_path, "commit", "-qam", "the code changes")
    (results / "new" / "table.md").write_text("rerun")
    (results / "recorded" / "r.json").write_text(json.dumps({"commit": git(tmp_path, "rev-parse", "--short", "HEAD")}))
    git(tmp_path, "add", "-A")
    git(tmp_path, "commit", "-qm", "results made on the new code")
    assert stale(tmp_path) == {"old": True, "new": False, "recorded": False}
    (results / "recorded" / "r.json").write_text(json.dumps({"commit": first}))  # it says it ran on the old code
    git(tmp_path, "commit", "-qam", "edit")
    assert stale(tmp_path)["recorded"] is True


def test_a_commit_listed_as_neutral_does_not_make_results_stale(tmp_path):
    git(tmp_path, "init", "-q")
    (tmp_path / "stepnft").mkdir()
    (tmp_path / "stepnft" / "core.py").write_text("x = 1\n")
    results = tmp_path / "benchmarks" / "results"
    (results / "table").mkdir(parents=True)
    (results / "table" / "t.json").write_text("{}")
    git(tmp_path, "add", "-A")
    git(tmp_path, "commit", "-qm", "code")
    (results / "table" / "t.json").write_text(json.dumps({"commit": git(tmp_path, "rev-parse", "--short", "HEAD")}))
    git(tmp_path, "commit", "-qam", "results")
    (tmp_path / "stepnft" / "core.py").write_text("x = 1  # renamed, same numbers\n")
    git(tmp_path, "commit", "-qam", "a refactor")
    assert stale(tmp_path) == {"table": True}
    refactor = git(tmp_path, "rev-parse", "--short", "HEAD")
    (results / "neutral_commits.txt").write_text(f"# commit  how it was checked\n{refactor}  metrics bit for bit\n")
    assert stale(tmp_path) == {"table": False}
    (tmp_path / "stepnft" / "core.py").write_text("x = 2\n")
    git(tmp_path, "commit", "-qam", "the numbers change")
    assert stale(tmp_path) == {"table": True}


def test_a_config_file_counts_only_for_folders_whose_commands_read_it(tmp_path):
    git(tmp_path, "init", "-q")
    (tmp_path / "stepnft").mkdir()
    (tmp_path / "stepnft" / "core.py").write_text("x = 1\n")
    (tmp_path / "configs").mkdir()
    for name in ("a.yaml", "b.yaml"):
        (tmp_path / "configs" / name).write_text("lr: 1\n")
    git(tmp_path, "add", "-A")
    git(tmp_path, "commit", "-qm", "code")
    head = git(tmp_path, "rev-parse", "--short", "HEAD")
    results = tmp_path / "benchmarks" / "results"
    commands = {"uses_a": "bench.py --config configs/a.yaml", "uses_b": "bench.py --config configs/b.yaml",
                "default_config": "bench.py --seeds 0", "no_command": None}
    for name, cmd in commands.items():
        (results / name).mkdir(parents=True)
        (results / name / "r.json").write_text(json.dumps({"commit": head} | ({"command": cmd} if cmd else {})))
    git(tmp_path, "add", "-A")
    git(tmp_path, "commit", "-qm", "results")
    (tmp_path / "configs" / "b.yaml").write_text("lr: 2\n")
    git(tmp_path, "commit", "-qam", "b changes")
    assert stale(tmp_path) == {"uses_a": False, "uses_b": True, "default_config": True, "no_command": True}
    (tmp_path / "stepnft" / "core.py").write_text("x = 2\n")
    git(tmp_path, "commit", "-qam", "the package changes")
    assert stale(tmp_path)["uses_a"] is True


def test_a_neutral_commit_may_name_the_folders_it_still_counts_for(tmp_path):
    git(tmp_path, "init", "-q")
    (tmp_path / "stepnft").mkdir()
    (tmp_path / "stepnft" / "core.py").write_text("x = 1\n")
    git(tmp_path, "add", "-A")
    git(tmp_path, "commit", "-qm", "code")
    head = git(tmp_path, "rev-parse", "--short", "HEAD")
    results = tmp_path / "benchmarks" / "results"
    for name in ("metaworld", "libero"):
        (results / name).mkdir(parents=True)
        (results / name / "r.json").write_text(json.dumps({"commit": head}))
    git(tmp_path, "add", "-A")
    git(tmp_path, "commit", "-qm", "results")
    (tmp_path / "stepnft" / "core.py").write_text("x = 1\ny = 2  # libero only\n")
    git(tmp_path, "commit", "-qam", "a libero change")
    change = git(tmp_path, "rev-parse", "--short", "HEAD")
    (results / "neutral_commits.txt").write_text(f"{change}  except:libero,vla  MetaWorld bit for bit\n")
    assert stale(tmp_path) == {"metaworld": False, "libero": True}


def test_the_environment_column_compares_recorded_packages_with_the_pins(tmp_path):
    git(tmp_path, "init", "-q")
    (tmp_path / "stepnft").mkdir()
    (tmp_path / "stepnft" / "core.py").write_text("x = 1\n")
    (tmp_path / "constraints.txt").write_text("# pins\nnumpy==2.4.6\ntorch==2.13.0\n")
    git(tmp_path, "add", "-A")
    git(tmp_path, "commit", "-qm", "code")
    head = git(tmp_path, "rev-parse", "--short", "HEAD")
    results = tmp_path / "benchmarks" / "results"
    pins = {"numpy": "2.4.6", "torch": "2.13.0+cpu", "mujoco": "3.3.0"}
    recorded = {"pinned": {"packages": pins, "cpu": {"aten_capability": "AVX2"}},
                "other": {"packages": {"numpy": "2.3.1", "torch": "2.13.0+cpu"}}, "before_pins": {},
                # one seed of a learning table computed with ATen's AVX-512 kernels
                "avx512": {"packages": pins, "runs": [{"cpu": {"aten_capability": "AVX2"}}, {"cpu": {"aten_capability": "AVX512"}}]}}
    for name, fields in recorded.items():
        (results / name).mkdir(parents=True)
        (results / name / "r.json").write_text(json.dumps({"commit": head, **fields}))
    git(tmp_path, "add", "-A")
    git(tmp_path, "commit", "-qm", "results")
    assert environments(tmp_path) == {"before_pins": "unrecorded", "other": "differs: numpy 2.3.1!=2.4.6",
                                      "pinned": "pinned", "avx512": "differs: ATen AVX512"}
    assert not any(stale(tmp_path).values())  # the environment column alone makes nothing stale
