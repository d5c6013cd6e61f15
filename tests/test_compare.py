"""``stepnft compare`` end to end on the bandit: one SFT per seed shared by every run, a crashed
run reported in the table without stopping the others, an interrupted comparison resumed
without rerunning anything finished, the report."""

import csv
import dataclasses
import json
import os
import shutil

import pytest

from stepnft.algos.variants import VARIANTS
from stepnft.cli import main
from stepnft.compare import mean_ci, t_quantile
from stepnft.config import save_config
from stepnft.demo_bandit import bandit_config
from stepnft.runs import read_metrics

pytestmark = pytest.mark.slow


CRASH = """
import os
if os.environ.get("STEPNFT_TEST_CRASH_GRPO"):
    import stepnft.algos.grpo as grpo

    def crash(self, batch):
        raise ValueError("injected crash in GRPO's update")

    grpo.GRPO.update = crash
"""
"""A ``sitecustomize`` for compare's children: GRPO's runs crash in their first update (an
error of the run, which compare reports while the others go on)."""


def bandit_base(path, envs=126):
    """A tiny bandit run config."""
    cfg = bandit_config(run_dir="unused", iterations=3, episodes_per_iteration=envs, checkpoint_every=1)
    cfg = dataclasses.replace(
        cfg, env=dataclasses.replace(cfg.env, envs_per_task=envs), demos=dataclasses.replace(cfg.demos, episodes=500),
        sft=dataclasses.replace(cfg.sft, steps=300), eval=dataclasses.replace(cfg.eval, episodes=200, every=2,
                                                                              during_episodes=126))
    save_config(cfg, path)
    return path


def compare_args(base, out, budget=3 * 126 * 2):
    return ["compare", "--config", str(base), "--algos", "stepnft,ppo,grpo", "--seeds", "0", "--env-steps",
            str(budget), "--jobs", "2", "--out", str(out)]


def snapshot(folder):
    return {p.relative_to(folder): (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted(folder.rglob("*"))
            if p.is_file()}


@pytest.fixture(scope="module", autouse=True)
def crashing_grpo(tmp_path_factory):
    site = tmp_path_factory.mktemp("site")
    (site / "sitecustomize.py").write_text(CRASH)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("STEPNFT_TEST_CRASH_GRPO", "1")
        patch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])))
        yield


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    root = tmp_path_factory.mktemp("compare")
    base = bandit_base(root / "base.yaml")
    out = root / "out"
    code = main(compare_args(base, out))
    return base, out, code


def test_crashed_run_is_reported_and_the_others_finish(first):
    _, out, code = first
    assert code == 1  # not every run finished
    status = json.loads((out / "status.json").read_text())
    assert status["grpo_seed0"]["state"] == "crashed" and status["grpo_seed0"]["rc"] == 2
    assert "injected crash in GRPO's update" in (out / "logs" / "grpo_seed0.log").read_text()
    for name in ("sft_seed0", "stepnft_seed0", "ppo_seed0"):
        assert status[name]["state"] == "finished", name
    report = (out / "comparison.md").read_text()
    assert "| grpo | 0/1 (1 crashed) |" in report and "`grpo_seed0`: exit code 2" in report
    rows = {(r["algorithm"], r["task"]): r for r in csv.DictReader((out / "comparison.csv").open())}
    assert rows[("grpo", "average")]["finished"] == "0" and rows[("grpo", "average")]["crashed"] == "1"
    assert float(rows[("ppo", "average")]["env_steps_mean"]) >= 3 * 126 * 2
    assert float(rows[("ppo", "average")]["learner_samples_per_s"]) > 0
    assert (out / "comparison.png").stat().st_size > 0


def test_every_run_starts_from_its_seeds_sft_policy(first):
    _, out, _ = first
    sft = json.loads((out / "sft" / "seed0" / "summary.json").read_text())["sft"]
    for algo in ("stepnft", "ppo"):
        run = out / "runs" / algo / "seed0"
        summary = json.loads((run / "summary.json").read_text())
        assert summary["tasks"]["bandit"]["before"] == sft["tasks"]["bandit"]  # same policy, same states
        assert (run / "sft_policy" / "model.safetensors").read_bytes() == \
            (out / "sft" / "seed0" / "policy" / "model.safetensors").read_bytes()
        assert summary["algorithm"] == algo
    rows = {r["algorithm"]: r for r in csv.DictReader((out / "comparison.csv").open()) if r["task"] == "average"}
    ppo = json.loads((out / "runs" / "ppo" / "seed0" / "summary.json").read_text())["average"]["after"]
    stepnft = json.loads((out / "runs" / "stepnft" / "seed0" / "summary.json").read_text())["average"]["after"]
    assert float(rows["ppo"]["diff_vs_stepnft_mean"]) == pytest.approx(ppo - stepnft, abs=1e-4)


def test_resume_reruns_nothing_finished(first, capsys):
    base, out, _ = first
    # Interrupt ppo after its second checkpoint: drop what it wrote after it.
    ppo = out / "runs" / "ppo" / "seed0"
    for name in ("summary.json", "learning_curve.png"):
        (ppo / name).unlink()
    shutil.rmtree(ppo / "policy")
    shutil.rmtree(ppo / "checkpoints" / "iter_000003")
    (ppo / "checkpoints" / "LATEST").write_text("iter_000002")
    kept = {d: snapshot(out / d) for d in ("sft", "runs/stepnft", "demos")}
    status_before = json.loads((out / "status.json").read_text())

    code = main(compare_args(base, out))
    assert code == 1  # grpo crashes again
    for d, files in kept.items():
        assert snapshot(out / d) == files, d
    status = json.loads((out / "status.json").read_text())
    assert status["stepnft_seed0"]["attempts"] == status_before["stepnft_seed0"]["attempts"] == 1
    assert status["ppo_seed0"]["attempts"] == 2 and status["ppo_seed0"]["state"] == "finished"
    assert status["grpo_seed0"]["attempts"] == 2
    assert "resuming" in (out / "logs" / "ppo_seed0.log").read_text().split("=== ")[-1]
    assert [r["iteration"] for r in read_metrics(ppo / "metrics.jsonl") if not r.get("final")] == [0, 1, 2, 3]
    log = capsys.readouterr().out
    assert "stepnft_seed0: kept (finished earlier)" in log and "sft_seed0: kept" in log


def test_a_rerun_with_other_settings_is_refused(first, capsys):
    base, out, _ = first
    assert main(compare_args(base, out, budget=999)) == 2
    assert "other settings (differs in: env_step_budget" in capsys.readouterr().err


def test_help_lists_every_variant(capsys):
    assert main(["compare", "--help"]) == 0
    out = capsys.readouterr().out
    for name, variant in VARIANTS.items():
        assert f"  {name} " in out and variant.about in out


def test_confidence_intervals():
    assert t_quantile(2) == pytest.approx(4.303) and t_quantile(1000) == pytest.approx(1.962, abs=1e-3)
    mean, lo, hi = mean_ci([0.2, 0.4, 0.6])
    assert mean == pytest.approx(0.4) and hi - mean == pytest.approx(4.303 * 0.2 / 3**0.5)
    assert mean_ci([0.9, 1.0, 1.0], 0.0, 1.0)[2] == 1.0 and mean_ci([0.5])[1] != mean_ci([0.5])[1]  # NaN


def test_suites_evaluate_every_final_policy_and_the_sft_start(tmp_path):
    base = bandit_base(tmp_path / "base.yaml", envs=128)
    out = tmp_path / "out"
    argv = ["compare", "--config", str(base), "--algos", "stepnft", "--seeds", "0", "--env-steps", str(128 * 2),
            "--jobs", "2", "--out", str(out), "--suites", "ind", "--suite-episodes", "128"]
    assert main(argv) == 0
    for row in ("sft", "stepnft"):
        result = json.loads((out / "suites" / row / "seed0" / "suites.json").read_text())
        assert result["suite"] == "ind" and result["tasks"]["bandit"]["episodes"] == 128
    report = (out / "suites.md").read_text()
    assert "| SFT (start) | 1 |" in report and "| stepnft | 1 |" in report and "ood_average" in report
    assert "--suites ind --suite-episodes 128" in report  # the command shown reproduces the table
