"""Rollout and validation success against env steps for several `stepnft train` runs, finished or stopped.

For comparing recipe attempts side by side (docs/gym.md's FetchPush attempts): reads each run
folder's ``metrics.jsonl`` (and ``summary.json`` where the run finished), prints a table (the
first and last iterations' rollout success, the validations, the test success before and after
with 95 % intervals) and writes ``OUT/curves.{md,png}`` with the command and commit. A run
folder given as ``NAME=PATH`` is labelled NAME.

    .venv/bin/python benchmarks/run_curves.py base=runs/a groups=runs/b --out benchmarks/results/attempts
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from provenance import command, commit

from stepnft.runs import read_metrics


def read_run(path: Path) -> dict:
    rows = read_metrics(path / "metrics.jsonl", drop_torn_tail=True)  # a stopped run may end mid-line
    rollout = [(r["env_steps"], r["iteration"], r["charts/rollout_success_rate"]) for r in rows
               if "charts/rollout_success_rate" in r]
    validation = [(r["env_steps"], r["iteration"], r["charts/validation_success_rate"]) for r in rows
                  if "charts/validation_success_rate" in r]
    summary = json.loads((path / "summary.json").read_text()) if (path / "summary.json").exists() else None
    return {"rollout": rollout, "validation": validation, "summary": summary}


def fmt_test(summary: dict | None, which: str) -> str:
    if summary is None:
        return "(stopped)" if which == "after" else "–"
    values = [t[which] for t in summary["tasks"].values()]
    if len(values) == 1:
        lo, hi = values[0]["ci95"]
        return f"{values[0]['success']:.2f} [{lo:.2f}, {hi:.2f}]"
    return f"{np.mean([v['success'] for v in values]):.2f} (average of {len(values)} tasks)"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="run folders, each PATH or NAME=PATH")
    p.add_argument("--window", type=int, default=5, help="iterations averaged for the first / last rollout success")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    runs = {}
    for spec in args.runs:
        name, _, path = spec.rpartition("=")
        runs[name or Path(path).name] = read_run(Path(path))
    w = args.window
    lines = ["# Runs side by side", "", f"Command: `{command()}` (commit {commit()}).", "",
             f"| run | iterations | rollout success, first {w} → last {w} iterations | validations (iteration: success) "
             "| test before | test after |", "|---|---|---|---|---|---|"]
    for name, run in runs.items():
        success = [s for _, _, s in run["rollout"]]
        first, last = np.mean(success[:w]), np.mean(success[-w:])
        vals = ", ".join(f"{i}: {s:.2f}" for _, i, s in run["validation"])
        lines.append(f"| {name} | {len(success)} | {first:.2f} → {last:.2f} | {vals} | "
                     f"{fmt_test(run['summary'], 'before')} | {fmt_test(run['summary'], 'after')} |")
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "curves.md").write_text(text)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for k, (name, run) in enumerate(runs.items()):
        color = f"C{k % 10}"
        steps = np.array([x for x, _, _ in run["rollout"]])
        success = np.array([s for _, _, s in run["rollout"]])
        smooth = np.convolve(success, np.ones(w) / w, mode="valid") if len(success) >= w else success
        axes[0].plot(steps[len(steps) - len(smooth):], smooth, color=color, label=name)
        if run["validation"]:
            axes[1].plot([x for x, _, _ in run["validation"]], [s for _, _, s in run["validation"]], "o-",
                         color=color, label=name)
    axes[0].set_title(f"rollout success (Flow-SDE), {w}-iteration mean", fontsize=9)
    axes[1].set_title("validation success (ODE)", fontsize=9)
    for ax in axes:
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=110)
    print(f"wrote {out / 'curves.md'}")


if __name__ == "__main__":
    main()
