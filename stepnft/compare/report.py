"""A comparison's report, from whatever has finished: ``comparison.md`` (success per task with
95 % CIs, paired differences, crashed runs), ``comparison.csv``, ``comparison.png`` (success
against env steps) and, with ``--suites``, ``suites.md`` (paired differences per suite and task, the
paper's claims and their verdicts)."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from stepnft.algos.variants import get_variant
from stepnft.compare.command import CompareCommand, command_line
from stepnft.compare.plan import SFT
from stepnft.compare.claims import CLAIMS, PAPER_PI0, verdict
from stepnft.compare.stats import mean_ci, paired_differences, summarise, summarise_suites
from stepnft.evaluate import format_ci
from stepnft.provenance import code_commit
from stepnft.runs import write_atomic
from stepnft.suites import SUITE_NAMES


def write_report(cmd: CompareCommand, out: Path, status: dict) -> dict:
    """``comparison.md``, ``comparison.csv`` and ``comparison.png`` (and ``suites.md``); returns
    :func:`~stepnft.compare.stats.summarise`'s summary."""
    summary = summarise(cmd, out, status)
    settings = json.loads((out / "compare.json").read_text())
    write_atomic(out / "comparison.md", comparison_markdown(cmd, summary, settings, status))
    write_atomic(out / "comparison.csv", comparison_csv(summary))
    plot_comparison(summary, settings["env_step_budget"], out / "comparison.png")
    if cmd.suites:
        write_suites_report(cmd, out, summary["reference"],
                            rewards={name: row["reward"] for name, row in summary["rows"].items()})
    return summary


def comparison_markdown(cmd: CompareCommand, summary: dict, settings: dict, status: dict) -> str:
    """The table of every row, the paired differences per task, the runs that crashed."""
    columns, ref, rows = summary["columns"], summary["reference"], summary["rows"]
    lines = [f"# Comparison: {', '.join(cmd.algos)}", "", f"    {command_line(cmd)}", "", f"Code: {code_version()}.", "",
             f"RL budget {settings['env_step_budget']:,} env steps per run; seeds {', '.join(map(str, cmd.seeds))}; "
             f"ODE evaluation on {settings['eval']['episodes']} fixed initial states per task. Success: mean over "
             "seeds [95 % t-interval over seeds]. Δ: paired difference to "
             f"`{ref}` from the same SFT policy per seed, on average over every (seed, task) pair [95 % t-interval].",
             "", "| algorithm | runs | " + " | ".join(columns) + f" | Δ vs {ref} | env steps | optimizer steps / "
             "iteration | reward signal | wall-clock (min) | learner samples/s |", "|---" * (len(columns) + 8) + "|"]
    for name, row in rows.items():
        runs = f"{row['finished']}/{row['runs']}" + (f" ({len(row['crashed'])} crashed)" if row["crashed"] else "")
        label = "SFT (start)" if name == SFT else name
        delta = format_ci(row["diff"]["average"], signed=True) if row["paired_seeds"] else "–"
        extra = "– | – | – | – | –" if name == SFT or not row["finished"] else (
            f"{row['env_steps']:,.0f} | {_number(row['update_steps'], '.1f')} | {row['reward'] or '–'} | "
            f"{_number(row['wall_clock_s'] / 60, '.1f')} | {_number(row['samples_per_s'], ',.0f')}")
        lines.append(f"| {label} | {runs} | " + " | ".join(format_ci(row["success"][c]) for c in columns)
                     + f" | {delta} | {extra} |")
    if cmd.variant_set:
        lines += ["", "Settings of single variants on top of their own (`--variant-set`): "
                  + "; ".join(f"{name}: " + ", ".join(f"{k}={v}" for k, v in fields.items())
                              for name, fields in cmd.variant_overrides().items()) + "."]
    others = [n for n in rows if n not in (SFT, ref) and rows[n]["paired_seeds"]]
    if others:
        lines += ["", f"Paired differences to `{ref}` per task (95 % t-interval over seeds):", "",
                  "| algorithm | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
        lines += [f"| {n} | " + " | ".join(format_ci(rows[n]["diff"][c], signed=True) for c in columns) + " |"
                  for n in others]
    missing = [(n, status.get(n, {})) for row in rows.values() for n in row["crashed"]]
    if missing:
        lines += ["", "Runs that crashed (rerun the same command to retry them):", ""]
        lines += [f"- `{n}`: exit code {s.get('rc')}, log `{s.get('log')}`" for n, s in missing]
    lines += ["", "Optimizer steps / iteration: the mean of the runs' `losses/update_steps`. Reward signal: what the "
              "algorithm learns from (`success`: the sparse outcome; `success + shaped`: the simulator's shaped "
              "reward too). Learner samples/s: recorded denoising transitions per second of update time. "
              "Wall-clock: the run's own time (runs shared the machine with the other jobs).", "",
              "![success against env steps](comparison.png)", ""]
    return "\n".join(lines)


def _number(x: float, spec: str) -> str:
    return "–" if math.isnan(x) else format(x, spec)


def code_version() -> str:
    """The commit of the package's checkout when the report is written, and whether ``stepnft/``
    differed from it (a rerun writes the report again: runs resumed then use that code)."""
    commit = code_commit()
    if commit is None:
        return "not a git checkout"
    return f"commit {commit.split('+')[0]}" + (" with uncommitted changes in stepnft/" if "+" in commit else "")


def comparison_csv(summary: dict) -> str:
    """One line per row and column (task or average): success and paired difference with their
    intervals, run counts, means of env steps, wall-clock, learner speed and optimizer steps per
    iteration, the reward signal."""
    ref, rows = summary["reference"], summary["rows"]
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["algorithm", "task", "runs", "finished", "crashed", "success_mean", "success_ci_lo",
                     "success_ci_hi", f"diff_vs_{ref}_mean", "diff_ci_lo", "diff_ci_hi", "paired_seeds",
                     "env_steps_mean", "wall_clock_s_mean", "learner_samples_per_s", "update_steps_per_iteration",
                     "reward_signal"])
    for name, row in rows.items():
        for c in summary["columns"]:
            diff = row["diff"][c] if row["paired_seeds"] else (math.nan,) * 3
            numbers = [*row["success"][c], *diff, row["paired_seeds"], row["env_steps"], row["wall_clock_s"],
                       row["samples_per_s"], row["update_steps"]]
            writer.writerow([name, c, row["runs"], row["finished"], len(row["crashed"]),
                             *("" if isinstance(x, float) and math.isnan(x) else round(x, 4) for x in numbers),
                             row["reward"] or ""])
    return buffer.getvalue()


def write_suites_report(cmd: CompareCommand, out: Path, reference: str, rewards: dict | None = None) -> dict:
    """``suites.md``: success per suite and the OOD average (mean [95 % t-interval] over seeds)
    per algorithm, the reward signal each learns from (``rewards``, by row), the paired OOD
    difference to the reference (the paper's table shape), the paired differences per suite and
    task (:func:`task_differences_markdown`), then the paper's π0 table beside
    ours with a verdict per claim (:mod:`stepnft.compare.claims`); returns
    :func:`~stepnft.compare.stats.summarise_suites`'s rows."""
    rows = summarise_suites(cmd, out, reference)
    rewards = rewards or {}
    columns = [*SUITE_NAMES, "ood_average"]
    lines = [f"# Suites: {', '.join(cmd.suites)}", "", f"    {command_line(cmd)}", "",
             f"ODE evaluation of each final policy (and each SFT start), {cmd.suite_episodes} episodes per task and "
             "suite; mean over seeds [95 % t-interval]. OOD average: the mean of the vision, semantic and execution "
             f"suites that apply. Δ OOD: paired difference to `{reference}`. Reward signal: what the algorithm "
             "learns from (`success`: the sparse outcome; `success + shaped`: the shaped reward too).", "",
             "| algorithm | seeds | " + " | ".join(columns) + f" | Δ OOD vs {reference} | reward signal |",
             "|---" * (len(columns) + 4) + "|"]
    for name, row in rows.items():
        cells = [format_ci(row["success"][c]) for c in columns]
        delta = "–" if row["ood_diff"] is None else format_ci(row["ood_diff"], signed=True)
        lines.append(f"| {'SFT (start)' if name == SFT else name} | {row['seeds']} | " + " | ".join(cells)
                     + f" | {delta} | {'–' if name == SFT else rewards.get(name) or '–'} |")
    lines += task_differences_markdown(rows, reference)
    lines += claims_markdown(rows, cmd.algos, reference)
    write_atomic(out / "suites.md", "\n".join(lines) + "\n")
    return rows


def task_differences_markdown(rows: dict, reference: str) -> list[str]:
    """Each row minus ``reference`` per suite and task, paired by seed (95 % t-interval over
    seeds; ``average``: over every (seed, task) pair): ``[]`` without a paired seed."""
    ref = rows.get(reference, {}).get("per_task", {})
    body, tasks = [], []
    for name, row in rows.items():
        if name == reference:
            continue
        for suite in SUITE_NAMES:
            pairs = {s: (r[suite], ref[s][suite]) for s, r in row.get("per_task", {}).items()
                     if suite in r and suite in ref.get(s, {})}
            if not pairs:
                continue
            names = sorted({t for mine, theirs in pairs.values() for t in mine if t in theirs})
            tasks += [t for t in names if t not in tasks]
            diffs = {t: paired_differences({s: mine.get(t) for s, (mine, _) in pairs.items()},
                                           {s: theirs.get(t) for s, (_, theirs) in pairs.items()})
                     for t in names}
            body.append((name, suite, len(pairs), {t: mean_ci(d, -1.0, 1.0) for t, d in diffs.items()}
                         | {"average": mean_ci([x for d in diffs.values() for x in d], -1.0, 1.0)}))
    if not body:
        return []
    lines = ["", f"## Paired differences to `{reference}` per suite and task", "",
             f"Each row minus `{reference}` on the same seed (same SFT start), 95 % t-interval over seeds; average: "
             "over every (seed, task) pair.", "",
             "| algorithm | suite | paired seeds | " + " | ".join([*tasks, "average"]) + " |",
             "|---" * (len(tasks) + 4) + "|"]
    for name, suite, n, diff in body:
        cells = [format_ci(diff[t], signed=True) if t in diff else "–" for t in [*tasks, "average"]]
        lines.append(f"| {'SFT (start)' if name == SFT else name} | {suite} | {n} | " + " | ".join(cells) + " |")
    return lines


def claims_markdown(rows: dict, algos: list[str], reference: str) -> list[str]:
    """The paper's π0 ManiSkill table, then each claim tested on π-StepNFT − each PPO row (paired
    by seed): ``[]`` without a π-StepNFT and a PPO row among ``algos``."""
    ours = next((a for a in [reference, *algos] if a in algos and get_variant(a).algo == "stepnft"), None)
    critics = [a for a in algos if get_variant(a).algo == "ppo"]
    if ours is None or not critics:
        return []
    columns = [*SUITE_NAMES, "ood_average"]
    lines = ["", "## The paper's claims beside ours", "",
             "The paper (π0 on ManiSkill; success per suite):", "",
             "| paper | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    lines += [f"| {name} | " + " | ".join(f"{v[c]:.2f}" for c in columns) + " |" for name, v in PAPER_PI0.items()]
    lines += ["", f"Each claim tested here on `{ours}` minus each PPO row, paired by seed (same SFT start), 95 % "
              "t-interval over seeds: *reproduced*, *not reproduced*, or *inside the noise* (the interval cannot "
              "tell).", "", "| claim | pair | paired seeds | Δ [95 % CI] | verdict |", "|---|---|---|---|---|"]
    for critic in critics:
        for claim in CLAIMS:
            mine = {s: r[claim.suite] for s, r in rows[ours]["per_seed"].items()}
            if not any(v is not None for v in mine.values()):
                continue  # a suite this comparison did not run
            diffs = paired_differences(mine, {s: r[claim.suite] for s, r in rows[critic]["per_seed"].items()})
            diff = mean_ci(diffs, -1.0, 1.0)
            lines.append(f"| {claim.text} | {ours} − {critic} | {len(diffs)} | {format_ci(diff, signed=True)} | "
                         f"{verdict(claim, diff)} |")
    return lines


def plot_comparison(summary: dict, budget: int, path: Path) -> None:
    """Average ODE success against env steps: per algorithm the mean over seeds, band min-max."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(7, 4.5))
    grid = np.linspace(0, budget, 101)
    for name, row in summary["rows"].items():
        curves = [c for c in row["curves"].values() if c]
        if name == SFT or not curves:
            continue
        # Each run holds its last evaluation to the budget (it may stop a little past or short of it).
        ys = np.stack([np.interp(grid, *zip(*c)) for c in curves])
        line, = ax.plot(grid, ys.mean(axis=0), label=f"{name} ({len(curves)} seeds)")
        if len(curves) > 1:
            ax.fill_between(grid, ys.min(axis=0), ys.max(axis=0), color=line.get_color(), alpha=0.15)
    ax.set_xlabel("RL env steps")
    ax.set_ylabel("success rate (ODE evaluation, task average)")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    if ax.lines:
        ax.legend(loc="lower right", fontsize="small")
    ax.set_title("stepnft compare: mean over seeds, band min-max")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
