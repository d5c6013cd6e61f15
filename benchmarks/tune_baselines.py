"""The baselines' tuning: the four likelihood forms (``ppo``, ``ppo-one``, ``grpo``, ``grpo-one``)
under one small grid of trials, the same for every form, from the same SFT policy.

Every trial is one ``stepnft compare`` run on a short budget (default 0.3 M env steps, seed 0, the
README job's tasks and data per update) of the base configs ``configs/ppo.yaml`` /
``configs/grpo.yaml`` with a few ``algo`` fields changed, one factor at a time around them:
learning rate ×3 and ÷3, 4 epochs, a wider clip range, episode weighting off, and, for PPO, the
critic's loss as RLinf's (Huber δ = 10, value clipping 0.2). Every trial's config is written
to ``OUT/configs`` and its comparison's report to ``OUT/TRIAL-ALGO`` (the runs under ``--work``),
so each can be rerun alone; rerunning this script resumes.
Prints and writes ``OUT/tuning.md`` / ``tuning.json``: the average success of every form under
every trial, paired difference to the form's default trial with a 95 % interval over the
(task) pairs, and the best trial of each form.

    MUJOCO_GL=egl .venv/bin/python benchmarks/tune_baselines.py --out benchmarks/results/tune_baselines
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

from provenance import command, commit, cpu, packages

FORMS = ("ppo", "ppo-one", "grpo", "grpo-one")
BASES = {"ppo": "configs/ppo.yaml", "grpo": "configs/grpo.yaml"}

TRIALS: dict[str, dict] = {
    "default": {},
    "lr3e-4": {"lr": 3e-4},
    "lr3e-5": {"lr": 3e-5},
    "epochs4": {"update_epochs": 4},
    "clip0.5": {"clip_coef": 0.5},
    "no-episode-weighting": {"episode_weighting": False},
    "rlinf-critic": {"huber_delta": 10.0, "value_clip": 0.2},
}
"""Trial name -> ``algo`` fields changed from the base config (the same for every form)."""
PPO_ONLY = {"rlinf-critic"}
"""Trials that only PPO has a setting for."""


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--trials", nargs="+", default=list(TRIALS), choices=list(TRIALS), help="trials to run, in order")
    p.add_argument("--forms", nargs="+", default=list(FORMS), choices=list(FORMS), help="likelihood forms to tune")
    p.add_argument("--seed", type=int, default=0, help="the SFT policy's seed (one per trial and form)")
    p.add_argument("--env-steps", type=int, default=300_000, help="RL env-step budget of every run")
    p.add_argument("--eval-episodes", type=int, default=50, help="test episodes per task before and after RL")
    p.add_argument("--jobs", type=int, default=0, help="runs at once (stepnft compare --jobs)")
    p.add_argument("--table-only", action="store_true", help="only table the trials already run")
    p.add_argument("--work", default="runs/tune_baselines", help="folder for the comparisons' runs (large)")
    p.add_argument("--out", default="benchmarks/results/tune_baselines",
                   help="folder for the trial configs, each comparison's report and the table")
    return p.parse_args(argv)


def trial_config(trial: str, algo: str, out: Path) -> Path:
    """Write and return the base config of ``algo`` with ``trial``'s fields changed."""
    cfg = yaml.safe_load(Path(BASES[algo]).read_text())
    cfg["algo"].update(TRIALS[trial])
    path = out / "configs" / f"{trial}-{algo}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"# {BASES[algo]} with {TRIALS[trial] or 'nothing'} changed (benchmarks/tune_baselines.py)\n"
                    + yaml.safe_dump(cfg, sort_keys=False))
    return path


def run_trial(trial: str, forms: list[str], args: argparse.Namespace, out: Path) -> None:
    """One ``stepnft compare`` per algorithm of ``forms`` (its base config carries the trial)."""
    for algo in BASES:
        algos = [f for f in forms if f.split("-")[0] == algo and not (trial in PPO_ONLY and algo != "ppo")]
        if not algos:
            continue
        config = trial_config(trial, algo, out)
        cmd = [str(Path(sys.executable).parent / "stepnft"), "compare", "--config", str(config), "--algos", *algos,
               "--seeds", str(args.seed), "--env-steps", str(args.env_steps), "--eval-episodes",
               str(args.eval_episodes), "--jobs", str(args.jobs), "--reference", algos[0],
               "--out", str(Path(args.work) / f"{trial}-{algo}")]
        print("+", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)
        report = out / f"{trial}-{algo}"
        report.mkdir(exist_ok=True)
        for name in ("comparison.md", "comparison.csv", "comparison.png"):
            shutil.copy(Path(args.work) / f"{trial}-{algo}" / name, report / name)


def read_success(folder: Path) -> dict[str, dict[str, float]]:
    """``{variant: {task: success}}`` of a comparison's final policies (and ``sft``)."""
    path = folder / "comparison.csv"
    if not path.exists():
        return {}
    rows: dict[str, dict[str, float]] = {}
    with path.open() as f:
        for row in csv.DictReader(f):
            if row["task"] != "average" and row["success_mean"]:
                rows.setdefault(row["algorithm"], {})[row["task"]] = float(row["success_mean"])
    return rows


def update_stats(work: Path, trial: str, form: str, seed: int) -> str:
    """Mean approx-KL, clip fraction and optimizer steps per iteration of one run (its metrics.jsonl)."""
    path = work / f"{trial}-{form.split('-')[0]}" / "runs" / form / f"seed{seed}" / "metrics.jsonl"
    if not path.exists():
        return "–"
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]

    def mean(key: str) -> float:
        values = [r[key] for r in rows if isinstance(r.get(key), (int, float)) and math.isfinite(r[key])]
        return statistics.fmean(values) if values else math.nan

    return f"{mean('losses/approx_kl'):.3g} / {mean('losses/clipfrac'):.2f} / {mean('losses/update_steps'):.1f}"


def paired(a: dict[str, float], b: dict[str, float]) -> tuple[float, float, float]:
    """Mean of ``a - b`` over tasks with a 95 % t-interval (the same test states per task)."""
    diffs = [a[t] - b[t] for t in a if t in b]
    mean = statistics.fmean(diffs)
    if len(diffs) < 2:
        return mean, math.nan, math.nan
    from scipy import stats

    half = stats.t.ppf(0.975, len(diffs) - 1) * statistics.stdev(diffs) / math.sqrt(len(diffs))
    return mean, mean - half, mean + half


def table(args: argparse.Namespace, out: Path) -> dict:
    results: dict[str, dict] = {}
    for trial in TRIALS:
        for algo in BASES:
            for variant, tasks in read_success(out / f"{trial}-{algo}").items():
                if variant == "sft":
                    results.setdefault("sft", tasks)
                else:
                    results.setdefault(variant, {})[trial] = tasks
    lines = [
        "# Baseline tuning: four likelihood forms, one grid of trials",
        "",
        f"    MUJOCO_GL=egl .venv/bin/python benchmarks/tune_baselines.py --seed {args.seed} --env-steps "
        f"{args.env_steps} --eval-episodes {args.eval_episodes} --out {args.out}",
        "",
        "(the trials ran in parts, each part this command with `--trials` naming its trials; rerunning it "
        f"resumes and tables. This table: `{command()}`.)",
        "",
        f"Commit {commit()}. Seed {args.seed} (one SFT policy, the same for every run), "
        f"{args.env_steps:,} RL env steps per run, {args.eval_episodes} test episodes per task; base configs "
        f"{', '.join(BASES.values())} as they were when the trial ran (each trial's exact config is in "
        f"`{args.out}/configs`); each trial changes the `algo` fields named in its column. Cells: "
        "average test success over the five tasks, and in brackets its paired difference to the form's "
        "`default` trial (same test states; 95 % t-interval over the five tasks). One seed and a short "
        "budget: a screen for settings that are clearly better or worse, not a ranking within noise.",
        "",
        "Trials (`algo` fields changed from the base config): " + "; ".join(
            f"`{t}` {', '.join(f'{k}={v}' for k, v in TRIALS[t].items()) or 'none'}" for t in TRIALS) + ".",
        "",
        "| form | SFT | " + " | ".join(TRIALS) + " | best |",
        "|---|---|" + "---|" * len(TRIALS) + "---|",
    ]
    sft = results.get("sft", {})
    best: dict[str, str] = {}
    for form in FORMS:
        trials = results.get(form, {})
        if not trials:
            continue
        cells = []
        for trial in TRIALS:
            if trial not in trials:
                cells.append("–")
                continue
            avg = statistics.fmean(trials[trial].values())
            if trial != "default" and "default" in trials:
                d, lo, hi = paired(trials[trial], trials["default"])
                cells.append(f"{avg:.2f} ({d:+.2f} [{lo:+.2f}, {hi:+.2f}])")
            else:
                cells.append(f"{avg:.2f}")
        best[form] = max(trials, key=lambda t: statistics.fmean(trials[t].values()))
        start = f"{statistics.fmean(sft.values()):.2f}" if sft else "–"
        lines.append(f"| {form} | {start} | " + " | ".join(cells) + f" | {best[form]} |")
    lines += ["", "How far each update moved (mean over the run's iterations): approx-KL / clip fraction / "
              "optimizer steps per iteration.", "",
              "| form | " + " | ".join(TRIALS) + " |", "|---|" + "---|" * len(TRIALS)]
    for form in FORMS:
        if form in results:
            lines.append(f"| {form} | " + " | ".join(update_stats(Path(args.work), t, form, args.seed) for t in TRIALS) + " |")
    text = "\n".join(lines) + "\n"
    (out / "tuning.md").write_text(text)
    (out / "tuning.json").write_text(json.dumps({"trials": TRIALS, "success": results, "best": best,
                                                 "commit": commit(), "command": command(), "packages": packages(), "cpu": cpu()}, indent=1))
    print(text)
    return results


def main(argv=None) -> None:
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not args.table_only:
        for trial in args.trials:
            run_trial(trial, args.forms, args, out)
    table(args, out)


if __name__ == "__main__":
    main()
