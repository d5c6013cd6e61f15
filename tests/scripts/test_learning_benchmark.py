"""benchmarks/learning.py: a fresh clone (no run folders, only the committed learning.json)
adds seeds to a published table and pairs with published folders, without rerunning them."""

import json

import pytest

from benchmark_loader import ROOT, benchmark_module

TASKS = ["reach-v3", "push-v3"]


@pytest.fixture(scope="module")
def learning():
    with benchmark_module("learning") as module:
        yield module


def run(seed: int, before: float, after: float) -> dict:
    task = lambda b, a: {"before": {"success": b, "ci95": [b, b]}, "after": {"success": a, "ci95": [a, a]},  # noqa: E731
                         "best": {"success": a, "ci95": [a, a]}}
    return {"seed": seed, "run_dir": f"gone/seed{seed}", "tasks": {t: task(before, after) for t in TASKS},
            "average": {"before": before, "after": after, "best": after}, "below_start": [], "env_steps": 1000,
            "wall_clock_s": 60.0, "commit": "abc1234"}


def publish(folder, args: list[str], runs: list[dict], learning, packages: dict | None = None) -> None:
    folder.mkdir(parents=True)
    recorded = vars(learning.parse_args(args + ["--out", str(folder)]))
    packages = learning.packages() if packages is None else packages  # made on this environment by default
    (folder / "learning.json").write_text(json.dumps({"args": recorded, "packages": packages, "runs": runs}))


def would_train(learning, monkeypatch) -> list[int]:
    """Make ``learning.train`` raise "would train"; the seeds it was asked to train are listed."""
    seen = []

    def train(cfg, resume=False):
        seen.append(cfg.seed)
        raise RuntimeError("would train")

    monkeypatch.setattr(learning, "train", train)
    return seen


def test_recorded_seeds_are_reused_and_paired_without_their_folders(learning, tmp_path, monkeypatch):
    config = str(ROOT / "configs" / "quickstart.yaml")
    args = ["--config", config, "--tasks", *TASKS, "--set", "algo.labels=episode"]
    publish(tmp_path / "mine", args, [run(0, 0.4, 0.7)], learning)
    publish(tmp_path / "other", args[:-2], [run(0, 0.4, 0.5), run(1, 0.6, 0.9)], learning)

    def train(cfg, resume=False):
        raise AssertionError(f"seed {cfg.seed} was rerun although learning.json records it")

    monkeypatch.setattr(learning, "train", train)
    result = learning.main([*args, "--seeds", "0", "--out", str(tmp_path / "mine"),
                            "--paired-with", str(tmp_path / "other")])
    assert [r["seed"] for r in result["runs"]] == [0]
    assert result["runs"][0]["average"]["after"] == 0.7
    table = (tmp_path / "mine" / "learning.md").read_text()
    assert "| +0.20" in table  # 0.7 - 0.5 on both tasks, from other's learning.json alone
    assert (tmp_path / "mine" / "learning.png").is_file()
    assert table.rstrip().endswith("| same |")  # both started from the SFT policy of 0.4


def test_a_change_that_reaches_sft_is_paired_as_a_whole_recipe(learning, tmp_path, monkeypatch):
    """sft.image_shift=0 trains another SFT policy from the same demonstrations: the seeds still
    pair, and the table shows how far apart the SFT starts were."""
    config = str(ROOT / "configs" / "quickstart.yaml")
    args = ["--config", config, "--tasks", *TASKS, "--set", "sft.lr=0.001"]
    publish(tmp_path / "mine", args, [run(0, 0.3, 0.6), run(1, 0.5, 0.8)], learning)
    publish(tmp_path / "other", args[:-2], [run(0, 0.4, 0.5), run(1, 0.6, 0.9)], learning)
    monkeypatch.setattr(learning, "train", lambda cfg, resume=False: pytest.fail("reran a recorded seed"))
    learning.main([*args, "--seeds", "0", "1", "--out", str(tmp_path / "mine"), "--paired-with", str(tmp_path / "other")])
    row = (tmp_path / "mine" / "learning.md").read_text().rstrip().splitlines()[-1]
    assert "| 2 |" in row and "**+0.00" in row  # +0.1 and -0.1 on every task
    assert row.endswith("| -0.10 [-0.10, -0.10] (whole recipe) |")  # both SFT starts 0.1 lower


def test_a_recorded_seed_with_other_arguments_is_not_reused(learning, tmp_path, monkeypatch):
    config = str(ROOT / "configs" / "quickstart.yaml")
    publish(tmp_path / "mine", ["--config", config, "--tasks", *TASKS], [run(0, 0.4, 0.7)], learning)
    seen = would_train(learning, monkeypatch)
    with pytest.raises(RuntimeError, match="would train"):
        learning.main(["--config", config, "--tasks", *TASKS, "--set", "algo.labels=episode", "--seeds", "0",
                       "--out", str(tmp_path / "mine")])
    assert seen == [0]
    assert learning.recorded_runs(tmp_path / "mine")[0]["average"]["after"] == 0.7
    assert learning.finished_runs(tmp_path / "mine", [1]) == {}


def test_the_result_records_the_numeric_packages_versions(learning, tmp_path, monkeypatch):
    config = str(ROOT / "configs" / "quickstart.yaml")
    publish(tmp_path / "mine", ["--config", config, "--tasks", *TASKS], [run(0, 0.4, 0.7)], learning)
    monkeypatch.setattr(learning, "train", lambda cfg, resume=False: pytest.fail("reran a recorded seed"))
    result = learning.main(["--config", config, "--tasks", *TASKS, "--seeds", "0", "--out", str(tmp_path / "mine")])
    import torch
    assert result["packages"]["torch"] == torch.__version__
    assert set(result["packages"]) >= {"numpy", "mujoco", "metaworld"}
    assert result["cpu"]["aten_capability"] == torch.backends.cpu.get_cpu_capability() != "AVX512"  # stepnft's cap
    assert result["cpu"]["onednn_max_cpu_isa"] == "AVX2"


def test_a_recorded_seed_from_other_package_versions_is_rerun(learning, tmp_path, monkeypatch):
    """The same code gave another SFT start with other numpy/scipy/...: such a seed runs again."""
    config = str(ROOT / "configs" / "quickstart.yaml")
    args = ["--config", config, "--tasks", *TASKS]
    other = {**learning.packages(), "numpy": "0.0.1"}
    publish(tmp_path / "mine", args, [run(0, 0.4, 0.7)], learning, packages=other)
    seen = would_train(learning, monkeypatch)
    with pytest.raises(RuntimeError, match="would train"):
        learning.main([*args, "--seeds", "0", "--out", str(tmp_path / "mine")])
    assert seen == [0]
    assert learning.recorded_runs(tmp_path / "mine")[0]["average"]["after"] == 0.7  # still readable for pairing


def test_a_recorded_seed_computed_with_other_kernels_is_rerun(learning, tmp_path, monkeypatch):
    """ATen's AVX-512 kernels moved the main command's RL run (docs/experiments.md §14): a seed
    recorded with another dispatch level runs again; one recorded before the level was kept is reused."""
    config = str(ROOT / "configs" / "quickstart.yaml")
    args = ["--config", config, "--tasks", *TASKS]
    avx512 = {**run(0, 0.4, 0.7), "cpu": {"aten_capability": "AVX512"}}
    here = {**run(1, 0.4, 0.8), "cpu": learning.cpu()}
    publish(tmp_path / "mine", args, [avx512, here, run(2, 0.5, 0.9)], learning)
    assert sorted(learning.recorded_runs(tmp_path / "mine", learning.parse_args(args + ["--out", str(tmp_path / "mine")]))) == [1, 2]
    seen = would_train(learning, monkeypatch)
    with pytest.raises(RuntimeError, match="would train"):
        learning.main([*args, "--seeds", "1", "2", "0", "--out", str(tmp_path / "mine")])
    assert seen == [0]


def test_metaworld_tasks_are_also_tabled_per_difficulty_split(learning):
    runs = [run(0, 0.4, 0.7), run(1, 0.2, 0.3)]  # reach (easy) and push (hard)
    for r in runs:
        r["tasks"]["push-v3"]["after"]["success"] = 0.1
    text = learning.split_table(runs, TASKS)
    assert "| easy | 1 | 0.30 ± 0.14 | 0.50 ± 0.28 | 0.20 ± 0.14 |" in text
    assert "| hard | 1 | 0.30 ± 0.14 | 0.10 ± 0.00 |" in text and "medium" not in text
    assert learning.split_table(runs, ["bandit"]) == ""


def interrupted_run(folder, seed: int) -> None:
    run = folder / f"seed{seed}"
    for name in ("iter_000010", "iter_000020"):
        (run / "checkpoints" / name).mkdir(parents=True)
        (run / "checkpoints" / name / "state.json").write_text(name)
    (run / "checkpoints" / "LATEST").write_text("iter_000020")
    (run / "tb").mkdir()
    (run / "tb" / "events").write_text("x" * 1000)
    (run / "metrics.jsonl").write_text('{"iteration": 20}\n')
    (run / "config.yaml").write_text("seed: 0\n")


def test_a_parked_seed_resumes_on_a_fresh_clone_from_its_last_checkpoint(learning, tmp_path, monkeypatch):
    out = tmp_path / "out"
    interrupted_run(out, 0)
    (out / "seed1").mkdir(parents=True)
    (out / "seed1" / "summary.json").write_text("{}")  # finished: nothing to park
    config = str(ROOT / "configs" / "quickstart.yaml")
    learning.main(["--config", config, "--seeds", "0", "1", "--out", str(out), "--park"])
    assert (out / "partial_seed0.tar.gz").is_file() and not (out / "partial_seed1.tar.gz").exists()
    assert json.loads((out / "partial_seed0.json").read_text())["checkpoint"] == "iter_000020"

    clone = tmp_path / "clone"  # what a fresh clone has: the committed partial, no run folder
    clone.mkdir()
    for name in ("partial_seed0.tar.gz", "partial_seed0.json"):
        (clone / name).write_bytes((out / name).read_bytes())
    resumed = []

    def train(cfg, resume=False):
        resumed.append(resume)
        raise RuntimeError("would train")

    monkeypatch.setattr(learning, "train", train)
    with pytest.raises(RuntimeError, match="would train"):
        learning.main(["--config", config, "--seeds", "0", "--out", str(clone)])
    assert resumed == [True]
    run = clone / "seed0"
    assert (run / "checkpoints" / "iter_000020" / "state.json").read_text() == "iter_000020"
    assert not (run / "checkpoints" / "iter_000010").exists() and not (run / "tb").exists()  # left out: not needed
    assert (run / "metrics.jsonl").is_file() and (run / "config.yaml").is_file()


def test_a_parked_seed_from_other_package_versions_is_refused(learning, tmp_path, monkeypatch):
    out = tmp_path / "out"
    interrupted_run(out, 0)
    config = str(ROOT / "configs" / "quickstart.yaml")
    learning.main(["--config", config, "--seeds", "0", "--out", str(out), "--park"])
    made = json.loads((out / "partial_seed0.json").read_text())
    (out / "partial_seed0.json").write_text(json.dumps(made | {"packages": {"torch": "0.0"}}))
    import shutil

    shutil.rmtree(out / "seed0")
    would_train(learning, monkeypatch)
    with pytest.raises(SystemExit) as exit_:
        learning.main(["--config", config, "--seeds", "0", "--out", str(out)])
    assert exit_.value.code == 2
    assert not (out / "seed0").exists()
