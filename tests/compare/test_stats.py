"""A comparison's statistics on hand-made run folders: differences paired by seed, only over
the seeds both rows finished, and the report's cells in the one CI format."""

import json
import math

import pytest

from stepnft.compare import CompareCommand, format_ci, mean_ci, paired_differences, summarise, write_report
from stepnft.evaluate import format_ci as evaluate_format_ci


def write_run(folder, success: dict[str, float], sft: bool = False, algo: str | None = None,
              update_steps: tuple[float, ...] = ()) -> None:
    """A finished run folder: its summary, metrics (one iteration per entry of ``update_steps``)
    and, with ``algo``, a config.yaml holding that ``algo`` section (YAML)."""
    folder.mkdir(parents=True)
    if algo is not None:
        (folder / "config.yaml").write_text(f"algo: {algo}\n")
    average = sum(success.values()) / len(success)
    if sft:
        summary = {"sft": {"tasks": {t: {"success": v} for t, v in success.items()}, "average": average}}
    else:
        summary = {"tasks": {t: {"after": {"success": v}} for t, v in success.items()},
                   "average": {"after": average}, "env_steps": 100}
        records = [{"env_steps": 50, "charts/samples": 10, "time/update_s": 2.0, "charts/validation_success_rate": 0.5}]
        records += [{"env_steps": 60 + i, "losses/update_steps": n} for i, n in enumerate(update_steps)]
        records += [{"env_steps": 100, "final": True, "losses/update_steps": 1000}]  # the final evaluation's record
        (folder / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    (folder / "summary.json").write_text(json.dumps(summary))


def test_paired_differences_take_the_seeds_both_have():
    assert paired_differences({0: 0.5, 1: 0.7, 2: None, 3: 0.2}, {0: 0.25, 1: None, 3: 0.5}) == [0.25, -0.3]


def test_rows_pair_each_variant_with_the_reference_seed_by_seed(tmp_path):
    (tmp_path / "compare.json").write_text(json.dumps({"env": {"tasks": ["a", "b"]}, "env_step_budget": 100,
                                                       "eval": {"episodes": 10}}))
    for seed in (0, 1, 2):
        write_run(tmp_path / "sft" / f"seed{seed}", {"a": 0.1, "b": 0.2}, sft=True)
        write_run(tmp_path / "runs" / "stepnft" / f"seed{seed}", {"a": 0.5 + 0.1 * seed, "b": 0.5},
                  algo="{name: stepnft, labels: progress}", update_steps=(18, 20))
    for seed in (0, 2):  # ppo's seed 1 did not finish
        write_run(tmp_path / "runs" / "ppo" / f"seed{seed}", {"a": 0.4, "b": 0.9}, algo="{name: ppo}",
                  update_steps=(6, 6, 6 + seed))
    cmd = CompareCommand(algos=["stepnft", "ppo"], seeds=[0, 1, 2])
    status = {"ppo_seed1": {"state": "crashed", "rc": 2}, "ppo_seed0": {"wall_clock_s": 60.0}}
    summary = summarise(cmd, tmp_path, status)
    ppo, stepnft = summary["rows"]["ppo"], summary["rows"]["stepnft"]
    assert summary["reference"] == "stepnft" and ppo["paired_seeds"] == 2 and stepnft["paired_seeds"] == 0
    assert ppo["finished"] == 2 and ppo["crashed"] == ["ppo_seed1"] and ppo["wall_clock_s"] == 60.0
    assert ppo["diff"]["a"] == mean_ci([0.4 - 0.5, 0.4 - (0.5 + 0.1 * 2)], -1.0, 1.0)
    # On average: every (seed, task) pair.
    assert ppo["diff"]["average"] == mean_ci([0.4 - 0.5, 0.4 - (0.5 + 0.1 * 2), 0.9 - 0.5, 0.9 - 0.5], -1.0, 1.0)
    assert ppo["samples_per_s"] == pytest.approx(5.0) and math.isnan(summary["rows"]["sft"]["env_steps"])
    # Optimizer steps per iteration: the mean over a run's iterations (not its final record), then over seeds.
    assert ppo["update_steps"] == pytest.approx((6 + 6 + 6 + 6 + 6 + 8) / 6) and stepnft["update_steps"] == 19
    assert (ppo["reward"], stepnft["reward"], summary["rows"]["sft"]["reward"]) == ("success", "success + shaped", None)

    write_report(cmd, tmp_path, status)
    report = (tmp_path / "comparison.md").read_text()
    assert f"| ppo | 2/3 (1 crashed) | {format_ci(ppo['success']['a'])} |" in report
    assert f"| {format_ci(ppo['diff']['average'], signed=True)} | 100 | 6.3 | success |" in report
    assert "| stepnft | 3/3 |" in report and "| – | 100 | 19.0 | success + shaped |" in report
    assert "update_steps_per_iteration,reward_signal" in (tmp_path / "comparison.csv").read_text()


def test_one_ci_format_everywhere():
    assert format_ci is evaluate_format_ci
    assert format_ci((0.5, 0.25, 0.75)) == "0.50 [0.25, 0.75]"
    assert format_ci((0.1, -0.05, 0.25), signed=True) == "+0.10 [-0.05, +0.25]"
    assert format_ci((0.5, math.nan, math.nan)) == "0.50" and format_ci((math.nan,) * 3) == "–"
