"""Why tasks whose SFT start is near zero fall under RL: per task, what the update saw.

Reads the run folders that ``benchmarks/learning.py --set algo.task_diagnostics=true`` wrote
(``OUT/seed*/metrics.jsonl``, ``summary.json``) and prints, per task and seed, the SFT start and
the final test success, then per quarter of the run: rollout success (Flow-SDE, the acting
policy), episodes the allocation gave it, the share of its recorded steps labelled positive, the
positives' share of its sample weight, E_pos, E_neg and ||v - v_old||. Writes ``OUT/diagnosis.md``
(the tables, the command, the commit) and ``OUT/diagnosis.png`` (those curves per task)::

    .venv/bin/python benchmarks/low_start.py --out benchmarks/results/low_start_diagnosis

``--out`` may be given several times (one figure line style per folder, e.g. the recipe and a fix).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from provenance import command, commit  # noqa: E402

CURVES = [("rollout", "rollout success (SDE)"), ("episodes", "episodes / iteration"),
          ("labels/pos_frac", "steps labelled > 0"), ("labels/weight_share", "positives' weight share"),
          ("losses/E_pos", "E_pos"), ("losses/E_neg", "E_neg"), ("losses/delta_v_norm", "||v - v_old||")]
"""Per-task metrics (``NAME/<task>`` in metrics.jsonl) and their labels."""


def read_run(run: Path) -> tuple[list[dict], dict]:
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line]
    return [r for r in records if "charts/SPS" in r], json.loads((run / "summary.json").read_text())


def quarter_means(records: list[dict], key: str) -> list[float]:
    """The mean of ``key`` over each quarter of the iterations (NaN where it is never logged)."""
    out = []
    for q in range(4):
        part = records[q * len(records) // 4:(q + 1) * len(records) // 4]
        values = [r[key] for r in part if r.get(key) is not None]
        out.append(sum(values) / len(values) if values else math.nan)
    return out


def table(out: Path) -> tuple[list[str], dict]:
    runs = sorted(p for p in out.glob("seed*") if (p / "summary.json").is_file())
    if not runs:
        raise SystemExit(f"{out}: no finished run folders (seed*/summary.json); run benchmarks/learning.py first")
    lines, data = [], {}
    for run in runs:
        records, summary = read_run(run)
        tasks = list(summary["tasks"])
        data[run.name] = (records, tasks)
        lines += [f"### {out.name}/{run.name}", "",
                  "| task | SFT | final | " + " | ".join(f"{label} (Q1→Q4)" for _, label in CURVES) + " |",
                  "|---|---|---|" + "---|" * len(CURVES)]
        for task in tasks:
            row = summary["tasks"][task]
            cells = []
            for key, _ in CURVES:
                q = quarter_means(records, f"{key}/{task}")
                cells.append(" → ".join("–" if math.isnan(v) else (f"{v:.0f}" if key == "episodes" else f"{v:.2f}")
                                        for v in q))
            lines.append(f"| {task} | {row['before']['success']:.2f} | {row['after']['success']:.2f} | "
                         + " | ".join(cells) + " |")
        lines.append("")
    return lines, data


def figure(folders: dict[Path, dict], path: Path) -> None:
    tasks = next(iter(next(iter(folders.values())).values()))[1]
    fig, axes = plt.subplots(len(CURVES), len(tasks), figsize=(2.6 * len(tasks), 1.9 * len(CURVES)), squeeze=False)
    for style, (out, data) in zip(["-", "--", ":"], folders.items()):
        for seed, (records, _) in data.items():
            x = [r["env_steps"] / 1e6 for r in records]
            for i, (key, label) in enumerate(CURVES):
                for j, task in enumerate(tasks):
                    y = [r.get(f"{key}/{task}") for r in records]
                    axes[i][j].plot(x, [math.nan if v is None else v for v in y], style, lw=0.8,
                                    label=f"{out.name} {seed}")
                    axes[0][j].set_title(task.removesuffix("-v3"), fontsize=8)
                    axes[i][0].set_ylabel(label, fontsize=7)
    for ax in axes.flat:
        ax.tick_params(labelsize=6)
    axes[-1][0].set_xlabel("env steps (M)", fontsize=7)
    axes[0][0].legend(fontsize=5)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", action="append", required=True, help="a benchmarks/learning.py results folder")
    args = parser.parse_args()
    folders, text = {}, [f"# Per-task diagnosis (commit {commit()})", "", f"    {command()}", ""]
    for out in map(Path, args.out):
        lines, folders[out] = table(out)
        text += lines
    first = Path(args.out[0])
    (first / "diagnosis.md").write_text("\n".join(text))
    figure(folders, first / "diagnosis.png")
    print("\n".join(text))
    print(f"wrote {first / 'diagnosis.md'} and diagnosis.png")


if __name__ == "__main__":
    main()
