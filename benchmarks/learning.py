"""Few-shot learning benchmark: SFT vs π-StepNFT on MetaWorld tasks, several seeds.

One multi-task policy per seed: scripted-expert demonstrations (seeded by the run seed) ->
few-shot SFT -> RL under the config's budget -> ODE evaluation of ``policy/`` and
``best_policy/`` on the fixed test initial states. Prints and writes, under ``--out``:
``learning.md`` (per task and seed: SFT -> final [95 % CI], the best policy, tasks that ended
below their start), ``learning.json`` and ``learning.png`` (validation success against env steps,
the average and every task, one line per seed). A seed whose run folder already holds
``summary.json`` is reused, so seeds can run in parallel invocations and be tabled at the end;
so is a seed that ``--out``'s committed ``learning.json`` records with the same arguments (run
folders are not committed: a fresh clone adds seeds to a published table without rerunning the
others), and ``--paired-with`` reads a folder's ``learning.json`` where its run folders are absent;
one that was interrupted resumes from its last checkpoint (one stopped before its first is
left for you to delete: another invocation may still be running it). Run folders end with the
machine: ``--park`` packs each interrupted seed (its last checkpoint, config, metrics and
policies; stop the invocation running it first) into ``OUT/partial_seedN.tar.gz``, which can be
committed, and the same command on a fresh clone unpacks it and resumes that seed where it
stopped.

    .venv/bin/python benchmarks/learning.py --config configs/quickstart.yaml --seeds 0 1 2
    .venv/bin/python benchmarks/learning.py --tasks button-press-topdown-v3 ... --out benchmarks/results/other
    .venv/bin/python benchmarks/learning.py --set algo.labels=episode --out benchmarks/results/learning_episode \
        --paired-with benchmarks/results/learning_quickstart
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import tarfile
import time
from pathlib import Path

import yaml

from provenance import command, commit, cpu, packages

from stepnft.config import DEFAULT_TASKS, TrainConfig, from_dict, load_config, read_yaml, to_dict
from stepnft.evaluate import format_ci
from stepnft.runs import read_metrics, save_panels, task_panels
from stepnft.train import train


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="configs/quickstart.yaml", help="base run config (YAML); flags below override it")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="one full run per seed")
    p.add_argument("--tasks", nargs="+", default=None, help="MetaWorld v3 tasks (default: the config's)")
    p.add_argument("--demos", type=int, default=None, help="demonstrations per task (default: the config's)")
    p.add_argument("--task-demos", nargs="*", default=None, metavar="TASK=N",
                   help="per-task demonstration counts, e.g. door-open-v3=1 (default: the config's)")
    p.add_argument("--env-steps", type=int, default=None, help="RL env-step budget per run (default: the config's)")
    p.add_argument("--eval-episodes", type=int, default=100, help="test episodes per task (>= 100 for reported figures)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                   help="config fields to change, as YAML values, e.g. algo.labels=progress")
    p.add_argument("--paired-with", nargs="*", default=[], metavar="DIR",
                   help="other result folders of this script (or of stepnft compare: its runs/VARIANT) with runs of "
                        "the same seeds: adds paired differences with 95 %% CIs (of RL alone where the SFT starts "
                        "match, else of the whole recipe, the SFT starts' difference beside it)")
    p.add_argument("--out", default="benchmarks/results/learning", help="folder for runs and the result table")
    p.add_argument("--park", action="store_true",
                   help="train nothing: pack each of --seeds whose run stopped after a checkpoint (stop the invocation "
                        "running it first) into OUT/partial_seedN.tar.gz, for a later session to resume")
    return p.parse_args(argv)


def park(out: Path, seed: int) -> Path | None:
    """An interrupted seed's run folder packed for another machine: its last checkpoint, config,
    metrics, language cache and policies (not its TensorBoard logs, not older checkpoints), with
    ``partial_seedN.json`` saying what parked it (the parking code's commit: the run folder does not
    record the commit its iterations ran on; a results README says it). None when the seed has finished or has no checkpoint."""
    run = out / f"seed{seed}"
    latest = run / "checkpoints" / "LATEST"
    if (run / "summary.json").is_file() or not latest.is_file():
        return None
    keep = latest.read_text().strip()

    def member(info: tarfile.TarInfo) -> tarfile.TarInfo | None:
        parts = Path(info.name).parts  # seedN/...
        if len(parts) > 1 and parts[1] == "tb":
            return None
        if len(parts) > 2 and parts[1] == "checkpoints" and parts[2] not in (keep, "LATEST"):
            return None
        return info

    path = out / f"partial_seed{seed}.tar.gz"
    with tarfile.open(path, "w:gz") as tar:
        tar.add(run, arcname=run.name, filter=member)
    (out / f"partial_seed{seed}.json").write_text(json.dumps(
        {"seed": seed, "checkpoint": keep, "parked_on_commit": commit(), "command": command(), "packages": packages(),
         "cpu": cpu()}, indent=2))
    return path


def unpark(out: Path, seed: int) -> bool:
    """Unpack ``OUT/partial_seedN.tar.gz`` where the seed's run folder is absent (a fresh clone),
    so that the seed resumes from the checkpoint it holds. Refused in one line when it was made
    with other versions of the packages that move the numbers."""
    path, run = out / f"partial_seed{seed}.tar.gz", out / f"seed{seed}"
    if run.exists() or not path.is_file():
        return False
    made = json.loads((out / f"partial_seed{seed}.json").read_text())
    if made.get("packages") != packages():
        _fail(f"{path} was made with {made.get('packages')}, this environment has {packages()}: resuming it would "
              "mix two sets of numbers in one run; delete it (and its .json) to run the seed from the start")
    with tarfile.open(path) as tar:
        tar.extractall(out, filter="data")
    print(f"learning.py: seed {seed}: resuming the parked run {path} ({made['checkpoint']}, parked on commit {made['parked_on_commit']})")
    return True


def with_fields(cfg: TrainConfig, items: list[str]) -> TrainConfig:
    """``cfg`` with ``KEY=VALUE`` fields changed (dotted keys, YAML values), checked as a config file is."""
    data = to_dict(cfg)
    for item in items:
        key, sep, value = item.partition("=")
        *sections, leaf = key.split(".")
        node = data
        for section in sections:
            node = node.get(section) if isinstance(node, dict) else None
        if not sep or not isinstance(node, dict):
            _fail(f"--set {item}: expected [SECTION.]FIELD=VALUE with an existing section, e.g. algo.labels=progress")
        node[leaf] = read_yaml(value)
    try:
        return from_dict(TrainConfig, data)
    except ValueError as err:
        _fail(f"--set: {err}")


def _fail(message: str) -> None:
    """Bad input: one line on stderr, exit code 2."""
    print(f"learning.py: {message}", file=sys.stderr)
    raise SystemExit(2)


def fmt(rates: list[float]) -> str:
    if len(rates) == 1:
        return f"{rates[0]:.2f}"
    return f"{statistics.mean(rates):.2f} ± {statistics.stdev(rates):.2f}"


def table(runs: list[dict], tasks: list[str]) -> str:
    """Markdown: per task, SFT / final / best over seeds, and each seed's figures with CIs."""
    cell = lambda r: format_ci((r["success"], *r["ci95"]))  # noqa: E731
    lines = ["| task | SFT | final | best (validation-chosen) | per seed: SFT → final [95 % CI] |", "|---|---|---|---|---|"]
    for task in tasks:
        rates = {w: [r["tasks"][task][w]["success"] for r in runs] for w in ("before", "after", "best")}
        seeds = "; ".join(f"s{r['seed']}: {r['tasks'][task]['before']['success']:.2f} → {cell(r['tasks'][task]['after'])}"
                          + (" ⚠" if task in r.get("below_start", []) else "") for r in runs)
        lines.append(f"| {task} | {fmt(rates['before'])} | {fmt(rates['after'])} | {fmt(rates['best'])} | {seeds} |")
    avg = {w: [r["average"][w] for r in runs] for w in ("before", "after", "best")}
    seeds = "; ".join(f"s{r['seed']}: {r['average']['before']:.2f} → {r['average']['after']:.2f}" for r in runs)
    lines.append(f"| **average** | {fmt(avg['before'])} | **{fmt(avg['after'])}** | {fmt(avg['best'])} | {seeds} |")
    below = {r["seed"]: r.get("below_start", []) for r in runs}
    lines.append("")
    lines.append("⚠ = ended below its SFT start: the 95 % interval of the difference (Newcombe) lies below 0. "
                 "Below start per seed: "
                 + "; ".join(f"s{s}: {', '.join(b) or 'none'}" for s, b in below.items()) + ".")
    return "\n".join(lines)


def split_table(runs: list[dict], tasks: list[str]) -> str:
    """Markdown: the average SFT start and final success per MetaWorld difficulty split (easy,
    medium, hard, very hard: the splits MT50 results are reported by), mean over the split's tasks
    and then over seeds; empty unless every task is a MetaWorld v3 task."""
    from stepnft.envs.metaworld.benchmarks import DIFFICULTY, MT50

    if not set(tasks) <= set(MT50):
        return ""
    lines = ["| split | tasks | SFT | final | final − SFT |", "|---|---|---|---|---|"]
    for split, members in DIFFICULTY.items():
        mine = [t for t in tasks if t in members]
        if not mine:
            continue
        mean = lambda r, w: statistics.mean(r["tasks"][t][w]["success"] for t in mine)  # noqa: E731
        before, after = [mean(r, "before") for r in runs], [mean(r, "after") for r in runs]
        lines.append(f"| {split.replace('_', ' ')} | {len(mine)} | {fmt(before)} | {fmt(after)} | "
                     f"{fmt([a - b for a, b in zip(after, before)])} |")
    return "\n".join(lines)


RUN_ARGS = ("config", "tasks", "demos", "task_demos", "env_steps", "eval_episodes", "set")
"""The arguments that define a seed's run (the others only say which seeds, where, and pairings)."""


def recorded_runs(folder: Path, args: argparse.Namespace | None = None) -> dict[int, dict]:
    """The finished runs ``folder/learning.json`` records, by seed ({} if none, or if ``args``
    is given and the file was made with other run-defining arguments or other versions of the
    packages that move the numbers: those seeds must run again here)."""
    path = Path(folder) / "learning.json"
    if not path.is_file():
        return {}
    recorded = json.loads(path.read_text())
    if args is not None and (any(recorded["args"].get(k) != getattr(args, k) for k in RUN_ARGS)
                             or recorded.get("packages") != packages()):
        return {}
    here = cpu()["aten_capability"] if args is not None else None
    return {r["seed"]: {k: v for k, v in r.items() if k not in ("seed", "run_dir")} for r in recorded["runs"]
            # a seed whose torch computed with other kernels (AVX-512 vs AVX2) gives other numbers: run it again
            if here is None or r.get("cpu", {}).get("aten_capability", here) == here}


def finished_runs(folder: Path, seeds: list[int]) -> dict[int, dict]:
    """Of ``seeds``, the finished runs in ``folder``, by seed: each one's ``summary.json``, else
    what ``learning.json`` records (read once)."""
    found = {s: r for s, r in recorded_runs(folder).items() if s in seeds}
    for seed in seeds:
        path = Path(folder) / f"seed{seed}" / "summary.json"
        if path.is_file():
            found[seed] = json.loads(path.read_text())
    return found


def paired_table(runs: list[dict], tasks: list[str], others: list[str]) -> str:
    """Markdown: this folder's final success minus each other folder's, seed by seed (the same
    demonstrations and test states), per task and on average over every (seed, task) pair, with 95 %
    t-intervals. Where the SFT starts differ (the change reaches SFT or the network), the difference
    is of the whole recipe, and the last column gives the SFT starts' own difference beside it."""
    from stepnft.compare import mean_ci

    lines = ["| this minus | seeds | " + " | ".join(tasks) + " | average | SFT start (this minus) |",
             "|---" * (len(tasks) + 4) + "|"]
    for other in others:
        diffs: dict[str, list[float]] = {t: [] for t in tasks}
        starts: list[float] = []
        seeds = []
        finished = finished_runs(Path(other), [r["seed"] for r in runs])
        for r in runs:
            theirs = finished.get(r["seed"])
            if theirs is None:
                continue
            seeds.append(r["seed"])
            for t in tasks:
                diffs[t].append(r["tasks"][t]["after"]["success"] - theirs["tasks"][t]["after"]["success"])
                starts.append(r["tasks"][t]["before"]["success"] - theirs["tasks"][t]["before"]["success"])
        every = [d for t in tasks for d in diffs[t]]
        same = all(abs(d) < 1e-9 for d in starts)
        lines.append(f"| {other} | {len(seeds)} | "
                     + " | ".join(format_ci(mean_ci(diffs[t], -1, 1), signed=True) for t in tasks)
                     + f" | **{format_ci(mean_ci(every, -1, 1), signed=True)}** | "
                     + ("same" if same else format_ci(mean_ci(starts, -1, 1), signed=True) + " (whole recipe)") + " |")
    return "\n".join(lines)


def curves(run_dir: Path, tasks: list[str]) -> dict[str, list]:
    """Validation success against env steps (the average and each task) from a run's metrics,
    kept in ``learning.json`` so that the figure can be redrawn without the run folder."""
    records = read_metrics(Path(run_dir) / "metrics.jsonl")
    keys = ["charts/validation_success_rate"] + [f"validation/{t}" for t in tasks]
    return {k: [[x["env_steps"], x[k]] for x in records if x.get(k) is not None] for k in keys}


def plot(out: Path, runs: list[dict], tasks: list[str]) -> Path:
    """The validation curves of every run that has them (a run recorded before they were kept
    in ``learning.json``, whose folder is not here, has none)."""
    panels = [("average", "charts/validation_success_rate")] + [(t, f"validation/{t}") for t in tasks]
    fig, axes = task_panels([p[0] for p in panels])
    for ax, (_, key) in zip(axes.flat, panels):
        for r in runs:
            points = r.get("curves", {}).get(key)
            if points:
                ax.plot(*zip(*points), marker="o", ms=2, label=f"seed {r['seed']}")
    return save_panels(fig, axes, "validation success (ODE) during π-StepNFT, per seed", out / "learning.png")


def main(argv=None) -> dict:
    args = parse_args(argv)
    base = with_fields(load_config(args.config), args.set)
    tasks = list(args.tasks or base.env.tasks or DEFAULT_TASKS)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    demos = base.demos
    if args.demos is not None:
        demos = dataclasses.replace(demos, episodes=args.demos)
    if args.task_demos is not None:
        demos = dataclasses.replace(demos, task_episodes={k: int(v) for k, v in (s.split("=") for s in args.task_demos)})
    if args.park:
        for seed in args.seeds:
            path = park(out, seed)
            print(f"learning.py: seed {seed}: " + (f"parked in {path}" if path else "nothing to park (finished, or "
                                                   "no checkpoint yet)"))
        return {}
    runs = []
    recorded = recorded_runs(out, args)  # published seeds whose run folders this checkout lacks
    for seed in args.seeds:
        cfg = dataclasses.replace(
            base, seed=seed, run_dir=str(out / f"seed{seed}"),
            env=dataclasses.replace(base.env, tasks=tasks),
            demos=dataclasses.replace(demos, seed=seed, path=str(out / f"demos_seed{seed}")),
            eval=dataclasses.replace(base.eval, episodes=args.eval_episodes),
            env_step_budget=args.env_steps if args.env_steps is not None else base.env_step_budget,
        )
        done = Path(cfg.run_dir) / "summary.json"
        if not done.is_file() and seed in recorded and not Path(cfg.run_dir).exists():
            print(f"learning.py: seed {seed}: the run {out / 'learning.json'} records (commit {recorded[seed].get('commit')})")
            runs.append({"seed": seed, "run_dir": cfg.run_dir, **recorded[seed]})
            continue
        if not done.is_file():  # finished earlier (or in a parallel invocation): reuse it
            unpark(out, seed)  # a run parked by an earlier session: its folder, to resume
            start = time.perf_counter()
            ran_on = commit()  # before training: the code may change (a commit, an edit) while a seed runs
            resume = (Path(cfg.run_dir) / "checkpoints" / "LATEST").is_file()  # interrupted: go on from there
            if not resume and Path(cfg.run_dir).exists() and any(Path(cfg.run_dir).iterdir()):
                # Stopped before its first checkpoint, or running in another invocation: never delete it here.
                sys.exit(f"learning.py: {cfg.run_dir} holds a run without a checkpoint (stopped before its first, or "
                         "still running in another invocation): once it is not running, delete it to run that seed again")
            summary = train(cfg, resume=resume)
            summary["wall_clock_s_this_session" if resume else "wall_clock_s"] = time.perf_counter() - start
            summary["commit"] = ran_on  # the code this seed ran on (this session's part of it, if resumed)
            summary["cpu"] = cpu()  # the CPU and the kernels torch used (this session's part, if resumed)
            done.write_text(json.dumps(summary, indent=2))
        summary = json.loads(done.read_text())
        runs.append({"seed": seed, "run_dir": cfg.run_dir, **summary, "curves": curves(Path(cfg.run_dir), tasks)})

    steps = [float(r["env_steps"]) for r in runs]
    own_counts = {t: n for t, n in demos.task_episodes.items() if t in tasks}  # the config's may name other tasks
    wall = [r.get("wall_clock_s", r.get("wall_clock_s_this_session", float("nan"))) for r in runs]
    splits = split_table(runs, tasks)
    text = (table(runs, tasks) + (f"\n\nPer difficulty split:\n\n{splits}" if splits else "")
            + f"\n\nRL env steps per run: {fmt(steps)}; wall-clock per run (demos, SFT, RL, "
            f"3 test evaluations of {args.eval_episodes} episodes/task): {statistics.mean(wall) / 60:.1f} min; "
            f"seeds {args.seeds}; demos/task {demos.episodes} {own_counts or ''}; config {args.config}"
            + (f" with {' '.join(args.set)}" if args.set else "") + f".\n\nCommand: `{command()}` (commit {commit()}).")
    if args.paired_with:
        text += "\n\nPaired differences of the final success (this minus the other, seed by seed: the same " \
                "demonstrations and test states; the average over every seed and task; where the SFT starts " \
                "differ, the difference is of SFT and RL together):\n\n" + paired_table(runs, tasks, args.paired_with)
    print(text)
    (out / "learning.md").write_text(text + "\n")
    plot(out, runs, tasks)
    result = {"command": command(), "commit": commit(), "packages": packages(), "cpu": cpu(), "args": vars(args), "tasks": tasks, "runs": runs,
              "average": {w: [r["average"][w] for r in runs] for w in ("before", "after", "best")}}
    (out / "learning.json").write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
