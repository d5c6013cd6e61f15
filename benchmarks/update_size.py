"""How far each update of a run moved its policy, read from the runs' ``metrics.jsonl``: per run
the first update's approx-KL and clip fraction, their medians over the later updates, the
rollout success of the first and of the last few iterations, and every validation success.

A screen for a learning rate that moves a policy too far (the first update's approx-KL in the
tens, most calls clipped, rollout success falling below its start) before a long run spends its
budget on it. It reads finished or unfinished runs, of ``stepnft train`` or ``stepnft compare``:

    .venv/bin/python benchmarks/update_size.py RUN_DIR [RUN_DIR ...] [--labels A B ...] [--out FOLDER]

writes FOLDER/update_size.md and .json (with this command and the commit it ran on), and prints the table.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import command, commit  # noqa: E402

from stepnft.runs import read_metrics  # noqa: E402


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="run folders (each with a metrics.jsonl)")
    p.add_argument("--labels", nargs="*", default=None,
                   help="one label per run (default: each folder's path below the folders' common parent)")
    p.add_argument("--last", type=int, default=5, help="iterations averaged as 'the last few' (default 5)")
    p.add_argument("--out", default=None, help="folder for update_size.md / .json (default: print only)")
    args = p.parse_args(argv)
    if args.labels is not None and len(args.labels) != len(args.runs):
        p.error(f"--labels: {len(args.labels)} labels for {len(args.runs)} runs")
    if args.labels is not None and len(set(args.labels)) != len(args.labels):
        p.error("--labels: each run needs its own label (a table row per label)")
    if len({Path(r).resolve() for r in args.runs}) != len(args.runs):
        p.error("a run folder is named twice")
    for run in args.runs:
        if not (Path(run) / "metrics.jsonl").is_file():
            p.error(f"{run}: no metrics.jsonl (not a run folder)")
    if args.last < 1:
        p.error("--last must be >= 1")
    return args


def default_labels(runs: list[str]) -> list[str]:
    """Each run's path below the runs' common parent (``ppo/seed1``, ``grpo/seed1``): the folder
    names alone collide across the variants of a comparison."""
    paths = [Path(r).resolve() for r in runs]
    if len(paths) == 1:
        return [paths[0].name]
    parent = Path(os.path.commonpath(paths))
    return [str(p.relative_to(parent)) for p in paths]


def summarise(run: Path, last: int) -> dict:
    """The update-size and success figures of one run folder."""
    records = [r for r in read_metrics(run / "metrics.jsonl") if not r.get("final")]
    updates = [r for r in records if r.get("iteration", 0) >= 1]
    kl = [r.get("losses/approx_kl") for r in updates]
    clip = [r.get("losses/clipfrac") for r in updates]
    rollout = [r["charts/rollout_success_rate"] for r in updates if r.get("charts/rollout_success_rate") is not None]
    later = [x for x in kl[1:] if x is not None]
    later_clip = [x for x in clip[1:] if x is not None]
    return {
        "run": str(run), "iterations": len(updates), "env_steps": records[-1].get("env_steps") if records else 0,
        "first_kl": kl[0] if kl else None, "first_clipfrac": clip[0] if clip else None,
        "later_kl_median": statistics.median(later) if later else None,
        "later_clipfrac_median": statistics.median(later_clip) if later_clip else None,
        "rollout_first": rollout[0] if rollout else None,
        "rollout_last": statistics.fmean(rollout[-last:]) if rollout else None,
        "validation": [(r["iteration"], r["charts/validation_success_rate"]) for r in records
                       if r.get("charts/validation_success_rate") is not None],
    }


def fmt(x, spec=".2f") -> str:
    return "–" if x is None else format(x, spec)


def table(rows: dict[str, dict], last: int) -> str:
    lines = [f"| run | iterations | env steps | approx-KL, 1st update | median later | clip fraction, 1st | median later "
             f"| rollout success, 1st iteration | last {last} | validation success (iteration) |",
             "|---" * 10 + "|"]
    for label, r in rows.items():
        validation = ", ".join(f"{v:.2f} ({i})" for i, v in r["validation"])
        lines.append(f"| {label} | {r['iterations']} | {r['env_steps']:,} | {fmt(r['first_kl'], '.3g')} | "
                     f"{fmt(r['later_kl_median'], '.3g')} | {fmt(r['first_clipfrac'])} | {fmt(r['later_clipfrac_median'])} | "
                     f"{fmt(r['rollout_first'])} | {fmt(r['rollout_last'])} | {validation} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    labels = args.labels or default_labels(args.runs)
    rows = {label: summarise(Path(run), args.last) for label, run in zip(labels, args.runs)}
    text = table(rows, args.last)
    print(text)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "update_size.md").write_text(
            f"# How far each update moved\n\n    {command()}\n\nTable made on commit {commit()}. "
            "approx-KL: `mean((r - 1) - log r)` over the update's minibatches; clip fraction: the share of calls "
            "clipped; 'later': the median over every update after the first.\n\n" + text + "\n")
        (out / "update_size.json").write_text(json.dumps({"command": command(), "commit": commit(), "runs": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
