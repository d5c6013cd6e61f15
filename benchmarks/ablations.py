"""The paper's ablations on MetaWorld: every π-StepNFT ablation against the project's default
(configs/quickstart.yaml) from the same SFT policy per seed, one table with the paper's claim,
ours and a verdict, and one figure of the curves.

One ``stepnft compare`` over every variant of :data:`ABLATIONS` (the runs under ``--work``),
seed by seed (all variants of the first seed finish before the next seed starts, so a partial
run is a whole table for fewer seeds); rerunning the same command resumes. The budget is a
stated fraction of the main command's (default 0.4 M of its ~1.3-1.5 M RL env steps; most of
the gain comes in its first 0.3 M): the EMA schedule keeps the main command's horizon, so the
default's run is the first part of a main-command run.
Prints and writes, under ``--out``: ``ablations.md`` (per ablation: the paper's figure, ours
with the paired difference to the default [95 % t-interval over every (seed, task) pair], the
verdict), ``ablations.json``, ``ablations.png`` (validation success against env steps, one
panel per question, mean over seeds) and the comparison's own report.

    MUJOCO_GL=egl .venv/bin/python benchmarks/ablations.py --out benchmarks/results/ablations
    MUJOCO_GL=egl .venv/bin/python benchmarks/ablations.py --table-only   # table what has finished

Verdict on a claim "the ablation is worse than the default" (sign -1) or "better" (+1):
``reproduced`` when the interval lies on the claimed side of 0, ``contradicted`` when it lies on
the other side, ``not separated`` when it contains 0 (with the measured difference: a small
interval around 0 says the two are level here, a wide one that the test could not tell).

A session's machine may not outlive the runs (3 seeds x 16 runs is ~3.5 h on 2 cores): after every
seed, and whenever the table is made, the small files of every finished run (summary, metrics,
config; each seed's SFT policy) are kept under ``OUT/finished/`` (committed with the table); a
rerun on a machine without ``--work`` restores them first, so only the unfinished runs run again
(from the seed's kept SFT policy).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import stepnft  # noqa: F401  - caps torch's CPU kernels before anything computes, so cpu() records the capped ones
from provenance import command, commit, cpu, packages


@dataclass(frozen=True)
class Ablation:
    variant: str
    """``stepnft compare`` variant (``stepnft compare --help``)."""
    question: str
    """The panel of the figure: which choice of the method it tests."""
    paper: str
    """What the paper reports (success read approximately from its figures; default first)."""
    sign: int
    """The paper's claim about this variant against the default: -1 worse, +1 better."""
    note: str = ""
    """How this row differs from the paper's, where it does."""


ABLATIONS: tuple[Ablation, ...] = (
    Ablation("ode", "exploration", "SDE ~0.85-0.9; ODE exploration plateaus ~0.75", -1),
    Ablation("sde-plain", "exploration", "SDE ~0.85-0.9; SDE without the mean correction ~0.4-0.5", -1),
    Ablation("x0", "target", "step-wise ~0.95; x0 target ~0.85 (α0 = 0.9), ~0 (α0 = 0.1)", -1,
             "our x0 target (as the authors' code) has no α0: one row"),
    Ablation("wmse", "objective", "ranking ~0.95; wMSE ~0.91", -1),
    Ablation("pos-only", "objective", "ranking ~0.95; positive branch alone ~0.9", -1),
    Ablation("neg-only", "objective", "ranking ~0.95; negative branch alone ~0.8 (slow)", -1),
    Ablation("noise-0.2", "noise level a", "a = 0.2 best; 0.3 and 0.5 ~0.8", +1,
             "our default is a = 0.5 (measured, docs/experiments.md): the claim read as 0.2 > 0.5"),
    Ablation("noise-1", "noise level a", "a = 0.2 best; 0.5 ~0.8 (1.0 not reported)", -1,
             "the paper's trend continued: 1.0 < 0.5"),
    Ablation("beta-0.5", "trust factor β", "β = 1 best", -1),
    Ablation("beta-2", "trust factor β", "β = 1 best (β 1-2 good)", -1),
    Ablation("beta-5", "trust factor β", "β = 1 best; β = 5 ~0.8", -1),
    Ablation("ema-off", "EMA", "decay 0.1 -> 0.995 best", -1),
    Ablation("ema-slow", "EMA", "decay 0.1 -> 0.995 best", -1, "slow: 0.5 -> 0.999"),
    Ablation("episode-labels", "labels", "one ±1 label per episode (the paper's; no progress labels)", -1,
             "not a paper ablation: does this project's per-call progress label beat the paper's?"),
)
"""Every ablation, in table order; ``stepnft`` (the default) is the reference."""
REFERENCE = "stepnft"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="configs/quickstart.yaml", help="the default π-StepNFT run config (YAML)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="one SFT policy per seed, run in order")
    p.add_argument("--variants", nargs="+", default=[a.variant for a in ABLATIONS],
                   choices=[a.variant for a in ABLATIONS], help="ablations to run (the default always runs)")
    p.add_argument("--env-steps", type=int, default=400_000, help="RL env-step budget of every run")
    p.add_argument("--eval-episodes", type=int, default=50, help="test episodes per task before and after RL")
    p.add_argument("--jobs", type=int, default=0, help="runs at once (stepnft compare --jobs; 0: one per core)")
    p.add_argument("--table-only", action="store_true", help="only table the runs already finished")
    p.add_argument("--work", default="runs/ablations", help="folder of the comparison's runs (large)")
    p.add_argument("--out", default="benchmarks/results/ablations", help="folder for the table and figure")
    return p.parse_args(argv)


def compare_argv(args: argparse.Namespace, seeds: list[int]) -> list[str]:
    return [str(Path(sys.executable).parent / "stepnft"), "compare", "--config", args.config,
            "--algos", REFERENCE, *args.variants, "--seeds", *map(str, seeds), "--env-steps", str(args.env_steps),
            "--eval-episodes", str(args.eval_episodes), "--jobs", str(args.jobs), "--reference", REFERENCE,
            "--out", args.work]


RUN_FILES = ("summary.json", "metrics.jsonl", "config.yaml", "run.json")
"""What is kept of a finished RL run: what the table, the curves and ``stepnft compare``'s resume read."""
SFT_FILES = ("summary.json", "config.yaml", "run.json", "policy/config.json", "policy/model.safetensors",
             "policy/processor.safetensors")
"""What is kept of a finished SFT run: its policy too (~0.8 MB a seed), the start of every run of
its seed, so the runs not finished yet continue from that very policy."""


def _finished(work: Path) -> list[tuple[Path, tuple[str, ...]]]:
    """The finished SFT and RL run folders of the comparison ``work`` (as ``job_state`` reads
    them), each with the files kept of it."""
    sft = sorted(d.parent for d in work.glob("sft/seed*/summary.json") if (d.parent / "policy").is_dir())
    runs = sorted(d.parent for d in work.glob("runs/*/seed*/summary.json"))
    return [(d, SFT_FILES) for d in sft] + [(d, RUN_FILES) for d in runs]


def _copy_run(src: Path, dest: Path, names: tuple[str, ...]) -> None:
    for name in names:
        if (src / name).is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src / name, dest / name)


def keep_finished(work: Path, keep: Path) -> int:
    """Copy the comparison's settings and status and the kept files of every finished run of
    ``work`` into ``keep``; the number of runs kept."""
    if not (work / "compare.json").is_file():
        return 0
    keep.mkdir(parents=True, exist_ok=True)
    for name in ("compare.json", "status.json"):
        if (work / name).is_file():
            shutil.copy(work / name, keep / name)
    runs = _finished(work)
    made_on, model = machines(keep), cpu()["model"]
    for run_dir, names in runs:
        name = str(run_dir.relative_to(work))
        _copy_run(run_dir, keep / name, names)
        # Runs are deterministic per CPU family, not across them (an Intel Xeon and an AMD EPYC
        # split at the first iteration, docs/experiments.md §13): which machine made each one.
        made_on.setdefault(name, model)
    (keep / "machines.json").write_text(json.dumps(made_on, indent=1, sort_keys=True))
    return len(runs)


def machines(keep: Path) -> dict[str, str]:
    """``{"runs/VARIANT/seedS": CPU model}`` of the runs kept (the machine that made each)."""
    path = keep / "machines.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def machines_line(made_on: dict[str, str]) -> str:
    """One sentence: which CPU made the runs of each seed."""
    per_seed: dict[str, set[str]] = {}
    for name, model in made_on.items():
        per_seed.setdefault(name.rsplit("seed", 1)[1], set()).add(model or "unknown CPU")
    if not per_seed:
        return "Machines: not recorded."
    return "Machines (runs are deterministic per CPU family, not across them): " + "; ".join(
        f"seed {seed} on {', '.join(sorted(models))}" for seed, models in sorted(per_seed.items())) + "."


def restore_finished(keep: Path, work: Path) -> int:
    """Put the runs kept in ``keep`` back into ``work`` where ``work`` lacks them (a new machine):
    ``stepnft compare`` then counts them finished. The number restored."""
    if not (keep / "compare.json").is_file():
        return 0
    work.mkdir(parents=True, exist_ok=True)
    for name in ("compare.json", "status.json"):
        if (keep / name).is_file() and not (work / name).is_file():
            shutil.copy(keep / name, work / name)
    n = 0
    for run_dir, names in _finished(keep):
        dest = work / run_dir.relative_to(keep)
        if (dest / "summary.json").is_file():
            continue
        if dest.exists():
            shutil.rmtree(dest)  # an unfinished attempt: the kept run replaces it
        dest.mkdir(parents=True)
        _copy_run(run_dir, dest, names)
        n += 1
    return n


def run(args: argparse.Namespace, keep: Path) -> None:
    """The comparison, one more seed per call: every variant of a seed before the next seed;
    finished runs kept in ``keep`` after each."""
    work = Path(args.work)
    for k in range(1, len(args.seeds) + 1):
        argv = compare_argv(args, args.seeds[:k])
        print("+", " ".join(argv), flush=True)
        subprocess.run(argv, check=True)
        keep_finished(work, keep)


def read_rows(work: Path) -> dict[str, dict]:
    """``{variant: {"success": mean, "diff": (mean, lo, hi), "seeds": n}}`` on the task average,
    from the comparison's ``comparison.csv`` (what has finished)."""
    path = work / "comparison.csv"
    rows: dict[str, dict] = {}
    if not path.exists():
        return rows
    with path.open() as f:
        for row in csv.DictReader(f):
            if row["task"] != "average" or not row["success_mean"]:
                continue
            diff = tuple(float(row[k]) if row[k] else math.nan
                         for k in (f"diff_vs_{REFERENCE}_mean", "diff_ci_lo", "diff_ci_hi"))
            rows[row["algorithm"]] = {"success": float(row["success_mean"]), "diff": diff,
                                      "seeds": int(row["finished"]), "paired": int(row["paired_seeds"] or 0)}
    return rows


def verdict(sign: int, diff: tuple[float, float, float]) -> str:
    """The paper's claim (``sign``: the ablation worse -1 or better +1 than the default) against
    our paired difference ``(mean, lo, hi)``."""
    _, lo, hi = diff
    if math.isnan(lo) or math.isnan(hi):
        return "–"
    if sign * lo > 0 and sign * hi > 0:
        return "reproduced"
    if sign * lo < 0 and sign * hi < 0:
        return "contradicted"
    return "not separated"


def curves(work: Path, variant: str) -> list[list[tuple[float, float]]]:
    """Validation success against env steps of every finished seed of ``variant``."""
    out = []
    for run_dir in sorted((work / "runs" / variant).glob("seed*")):
        if not (run_dir / "summary.json").exists():
            continue
        points = []
        for line in (run_dir / "metrics.jsonl").read_text().splitlines():
            r = json.loads(line)
            if r.get("charts/validation_success_rate") is not None and not r.get("final"):
                points.append((r["env_steps"], r["charts/validation_success_rate"]))
        out.append(points)
    return out


def plot(work: Path, budget: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    questions = list(dict.fromkeys(a.question for a in ABLATIONS))
    cols = 4
    fig, axes = plt.subplots(math.ceil(len(questions) / cols), cols, figsize=(4 * cols, 3.2 * math.ceil(len(questions) / cols)),
                             sharey=True, squeeze=False)
    grid = np.linspace(0, budget, 81)
    for ax, question in zip(axes.flat, questions):
        for name in [REFERENCE] + [a.variant for a in ABLATIONS if a.question == question]:
            runs = [c for c in curves(work, name) if len(c) > 1]
            if not runs:
                continue
            ys = np.stack([np.interp(grid, *zip(*c)) for c in runs])
            ax.plot(grid, ys.mean(axis=0), label=f"{name} ({len(runs)})", lw=2 if name == REFERENCE else 1.3,
                    color="black" if name == REFERENCE else None)
        ax.set_title(question)
        ax.set_xlabel("RL env steps")
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small", loc="lower right")
    for ax in axes.flat[len(questions):]:
        ax.axis("off")
    for ax in axes[:, 0]:
        ax.set_ylabel("validation success (ODE)")
    fig.suptitle("π-StepNFT ablations on five MetaWorld tasks: mean over seeds (count in brackets)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def refresh_report(args: argparse.Namespace, work: Path) -> None:
    """Write the comparison's report (comparison.md / .csv / .png) from the runs finished so far,
    as ``stepnft compare`` does when it ends: the table can be made while seeds still run."""
    if not (work / "compare.json").exists():
        return
    from stepnft.compare import CompareCommand
    from stepnft.compare.report import write_report

    cmd = CompareCommand(config=args.config, algos=[REFERENCE, *args.variants], seeds=args.seeds,
                         env_steps=args.env_steps, jobs=args.jobs, out=args.work, reference=REFERENCE,
                         eval_episodes=args.eval_episodes)
    status = json.loads((work / "status.json").read_text()) if (work / "status.json").exists() else {}
    write_report(cmd, work, status)


def table(args: argparse.Namespace, out: Path) -> dict:
    work = Path(args.work)
    refresh_report(args, work)
    rows = read_rows(work)
    ref, sft = rows.get(REFERENCE), rows.get("sft")
    lines = [
        "# π-StepNFT ablations on MetaWorld: the paper's claims, ours, the verdicts", "",
        f"    MUJOCO_GL=egl .venv/bin/python benchmarks/ablations.py --seeds {' '.join(map(str, args.seeds))} "
        f"--env-steps {args.env_steps} --eval-episodes {args.eval_episodes} --out {args.out}", "",
        f"(This table: `{command()}`; commit {commit()}.) Base config `{args.config}` (π-StepNFT's default, "
        f"row `{REFERENCE}`); each ablation changes one `algo` setting (`stepnft compare --help`). Five MetaWorld "
        f"tasks, every run of a seed from the same SFT policy, {args.env_steps:,} RL env steps per run (a fraction "
        "of the main command's ~1.3-1.5 M; the EMA schedule keeps the main command's 160-iteration horizon), "
        f"{args.eval_episodes} test episodes per task. Ours: average test success, mean over seeds; Δ: paired "
        f"difference to `{REFERENCE}` [95 % t-interval over every (seed, task) pair]. The paper's figures are "
        "read approximately from its plots (LIBERO / ManiSkill with a VLA, not these tasks): compare the "
        "direction, not the level.", "",
        f"Default `{REFERENCE}`: " + (f"{ref['success']:.2f} ({ref['seeds']} seeds); SFT start {sft['success']:.2f}."
                                      if ref and sft else "not finished yet."), "",
        machines_line(machines(out / "finished")), "",
        "| ablation | question | the paper | ours (seeds) | Δ vs default [95 % CI] | paper's claim | verdict | note |",
        "|---|---|---|---|---|---|---|---|",
    ]
    results = {}
    for a in ABLATIONS:
        row = rows.get(a.variant)
        if row is None:
            lines.append(f"| `{a.variant}` | {a.question} | {a.paper} | – | – | {'worse' if a.sign < 0 else 'better'} | "
                         f"not run yet | {a.note} |")
            continue
        mean, lo, hi = row["diff"]
        v = verdict(a.sign, row["diff"])
        results[a.variant] = {**row, "verdict": v, **asdict(a)}
        ci = f"{mean:+.2f} [{lo:+.2f}, {hi:+.2f}]" if not math.isnan(lo) else f"{mean:+.2f}"
        lines.append(f"| `{a.variant}` | {a.question} | {a.paper} | {row['success']:.2f} ({row['seeds']}) | {ci} | "
                     f"{'worse' if a.sign < 0 else 'better'} | {v} | {a.note} |")
    lines += ["", "![curves](ablations.png)", "", f"The comparison's own report (per task, per seed): `{work}` "
              "(copied here as comparison.md / .csv / .png).", ""]
    text = "\n".join(lines)
    (out / "ablations.md").write_text(text)
    (out / "ablations.json").write_text(json.dumps({"default": ref, "sft": sft, "ablations": results,
                                                    "env_steps": args.env_steps, "seeds": args.seeds,
                                                    "commit": commit(), "command": command(), "packages": packages(), "cpu": cpu()}, indent=1))
    for name in ("comparison.md", "comparison.csv", "comparison.png"):
        if (work / name).exists():
            shutil.copy(work / name, out / name)
    plot(work, args.env_steps, out / "ablations.png")
    print(text)
    return results


def main(argv=None) -> None:
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    keep, work = out / "finished", Path(args.work)
    restored = restore_finished(keep, work)
    if restored:
        print(f"restored {restored} finished run(s) from {keep} into {work}", flush=True)
    if not args.table_only:
        run(args, keep)
    keep_finished(work, keep)  # also the runs a stopped comparison finished
    table(args, out)


if __name__ == "__main__":
    main()
