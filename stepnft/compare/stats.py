"""A comparison's statistics: the finished runs' results (:func:`load_result`, :func:`load_sft`),
means with 95 % Student-t intervals over seeds (:func:`mean_ci`) and differences paired by
seed to the reference variant (:func:`paired_differences`), per row of the report
(:func:`summarise`, :func:`summarise_suites`)."""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path

from stepnft.algos.variants import reward_signal
from stepnft.compare.command import CompareCommand
from stepnft.compare.plan import SFT
from stepnft.config import load_config
from stepnft.runs import read_metrics
from stepnft.suites import SUITE_NAMES, summarize_suites

T_975 = [12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145, 2.131,
         2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042]
"""Student-t 0.975 quantiles for 1..30 degrees of freedom."""


def t_quantile(df: int) -> float:
    """Two-sided 95 % Student-t quantile (Cornish-Fisher beyond the table)."""
    return T_975[df - 1] if df <= len(T_975) else 1.96 + (1.96**3 + 1.96) / (4 * df)


def mean_ci(values: list[float], lo: float = -math.inf, hi: float = math.inf) -> tuple[float, float, float]:
    """Mean and 95 % t-interval, the interval cut to ``[lo, hi]`` (NaN bounds with fewer than
    two values)."""
    if not values:
        return math.nan, math.nan, math.nan
    mean = statistics.fmean(values)
    if len(values) < 2:
        return mean, math.nan, math.nan
    half = t_quantile(len(values) - 1) * statistics.stdev(values) / math.sqrt(len(values))
    return mean, max(lo, mean - half), min(hi, mean + half)


def paired_differences(values: dict[int, float | None], reference: dict[int, float | None]) -> list[float]:
    """``values[s] - reference[s]`` for every seed ``s`` (in ``values``' order) that both have."""
    return [v - reference[s] for s, v in values.items() if v is not None and reference.get(s) is not None]


def load_result(run_dir: Path) -> dict | None:
    """A finished run's after-RL success per task (and ``average``), env steps, evaluation curve
    ``[(env_steps, success)]``, learner samples/s, optimizer steps per iteration (the mean of
    ``losses/update_steps``) and the reward signal its config learns from (None without a
    ``config.yaml``); None if it did not finish."""
    if not (run_dir / "summary.json").is_file():
        return None
    summary = json.loads((run_dir / "summary.json").read_text())
    records = read_metrics(run_dir / "metrics.jsonl")
    update_s = sum(r.get("time/update_s") or 0.0 for r in records)
    samples = sum(r.get("charts/samples") or 0 for r in records)
    config = run_dir / "config.yaml"
    return {"success": {t: v["after"]["success"] for t, v in summary["tasks"].items()} | {
                "average": summary["average"]["after"]},
            "env_steps": summary["env_steps"],
            # Test states before and after, validation states during training.
            "curve": [(r["env_steps"], r.get("charts/validation_success_rate", r.get("charts/success_rate")))
                      for r in records if not r.get("final") and
                      r.get("charts/validation_success_rate", r.get("charts/success_rate")) is not None]
                     + [(summary["env_steps"], summary["average"]["after"])],
            "samples_per_s": samples / update_s if update_s > 0 else math.nan,
            "update_steps": _mean([r.get("losses/update_steps") for r in records if not r.get("final")]),
            "reward": reward_signal(load_config(config).algo) if config.is_file() else None}


def load_sft(run_dir: Path) -> dict | None:
    """A finished SFT run's success per task (and ``average``); None if it did not finish."""
    path = run_dir / "summary.json"
    if not path.is_file():
        return None
    result = json.loads(path.read_text())["sft"]
    return {"success": {t: v["success"] for t, v in result["tasks"].items()} | {"average": result["average"]}}


def summarise(cmd: CompareCommand, out: Path, status: dict) -> dict:
    """Per row (SFT, then each variant): per-seed results, success and paired-difference
    statistics per task and on average, run counts, means of env steps, wall-clock, speed and
    optimizer steps per iteration, the reward signal."""
    tasks = json.loads((out / "compare.json").read_text())["env"]["tasks"]
    columns = [*tasks, "average"]
    reference = cmd.reference if cmd.reference in cmd.algos else cmd.algos[0]
    per_seed = {SFT: {s: load_sft(out / "sft" / f"seed{s}") for s in cmd.seeds}}
    per_seed |= {a: {s: load_result(out / "runs" / a / f"seed{s}") for s in cmd.seeds} for a in cmd.algos}
    ref = {s: r for s, r in per_seed[reference].items() if r is not None}
    rows = {}
    for name, results in per_seed.items():
        done = {s: r for s, r in results.items() if r is not None}
        paired = [s for s in done if s in ref] if name not in (SFT, reference) else []
        diff = {c: paired_differences({s: done[s]["success"][c] for s in paired},
                                      {s: ref[s]["success"][c] for s in paired}) for c in columns}
        names = [f"{name}_seed{s}" for s in cmd.seeds]
        rows[name] = {
            "finished": len(done), "runs": len(results),
            "crashed": [n for n in names if status.get(n, {}).get("state") == "crashed"],
            "success": {c: mean_ci([r["success"][c] for r in done.values()], 0.0, 1.0) for c in columns},
            # Per task over seeds; on average over every (seed, task) pair.
            "diff": {c: mean_ci(diff[c], -1.0, 1.0) for c in tasks}
            | {"average": mean_ci([d for c in tasks for d in diff[c]], -1.0, 1.0)},
            "paired_seeds": len(paired),
            "env_steps": _mean([r.get("env_steps") for r in done.values()]),
            "wall_clock_s": _mean([status.get(n, {}).get("wall_clock_s") for n, s in zip(names, cmd.seeds)
                                   if s in done]),
            "samples_per_s": _mean([r.get("samples_per_s") for r in done.values()]),
            "update_steps": _mean([r.get("update_steps") for r in done.values()]),
            "reward": ", ".join(sorted({r["reward"] for r in done.values() if r.get("reward")})) or None,
            "curves": {s: r.get("curve") for s, r in done.items()},
        }
    return {"tasks": tasks, "columns": columns, "reference": reference, "rows": rows}


def summarise_suites(cmd: CompareCommand, out: Path, reference: str) -> dict:
    """Per row (SFT, then each variant): per-seed suite results (``OUT/suites/ROW/seedS``;
    ``per_seed``: success per suite and the OOD average, by seed; ``per_task``: by seed, suite
    and task), success per suite and the OOD
    average over seeds, and the OOD average's paired difference
    to ``reference`` (``None`` for the reference and for rows without a paired seed)."""
    table, per_task = {}, {}
    for row in [SFT, *cmd.algos]:
        per_seed = {}
        for seed in cmd.seeds:
            path = out / "suites" / row / f"seed{seed}" / "suites.json"
            if path.is_file():
                data = json.loads(path.read_text())  # one suite's result, or several under "suites"
                results = data["suites"] if "suites" in data else {data["suite"]: data}
                per_seed[seed] = summarize_suites(results)
                per_task.setdefault(row, {})[seed] = {name: {t: v["success"] for t, v in r.get("tasks", {}).items()}
                                                      for name, r in results.items() if "average" in r}
        table[row] = per_seed
    rows = {}
    for row, per_seed in table.items():
        ood = {s: r["ood_average"] for s, r in per_seed.items()}
        paired = paired_differences(ood, {s: r["ood_average"] for s, r in table.get(reference, {}).items()})
        rows[row] = {"seeds": len(per_seed), "per_seed": per_seed,
                     "per_task": per_task.get(row, {}),
                     "success": {c: mean_ci([r[c] for r in per_seed.values() if r[c] is not None], 0.0, 1.0)
                                 for c in [*SUITE_NAMES, "ood_average"]},
                     "ood_diff": mean_ci(paired, -1.0, 1.0) if paired and row != reference else None}
    return rows


def _mean(values: list) -> float:
    values = [v for v in values if v is not None and not math.isnan(v)]
    return statistics.fmean(values) if values else math.nan
