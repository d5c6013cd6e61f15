"""``stepnft compare``: algorithms and ablations side by side, on one env-step budget.

For every seed, few-shot SFT runs once (``stepnft sft``) and every variant
(``stepnft.algos.variants``) then trains from that same policy (``stepnft train --init``), on the
base config with the seed's demonstrations, the chosen tasks and the budget. Each run is its own
subprocess with one torch thread; ``--jobs`` of them run at once. The comparison folder::

    OUT/compare.json              the settings (a rerun must ask for the same ones)
    OUT/status.json               per run: state, exit code, attempts, wall-clock
    OUT/configs/NAME.yaml         the config each run was started with
    OUT/sft/seedS/                the SFT run of seed S (its policy/ is every run's --init)
    OUT/runs/VARIANT/seedS/       an ordinary stepnft run folder
    OUT/logs/NAME.log             stdout and stderr of every attempt
    OUT/comparison.md, .csv, .png the report

Rerunning the same command resumes: finished runs are kept, runs with a checkpoint continue
with ``stepnft train --resume``, the others start again. A run that crashes is reported in the
table (and retried by the next rerun); the others go on.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from stepnft.algos.variants import VARIANTS, describe_variants, variant_config

SFT = "sft"
"""The row of the SFT start in the report."""


@dataclass
class CompareCommand:
    """Compare RL fine-tuning algorithms and ablations from the same SFT start per seed, on one
    env-step budget: success per task with 95 % CIs, paired differences to the reference, env
    steps, wall-clock and learner speed (OUT/comparison.md, .csv, .png)."""

    config: str = "configs/quickstart.yaml"
    """Base run config (YAML): tasks, envs, demonstrations, policy, SFT, evaluation and the
    shared algorithm settings; each variant changes only its algo.* fields."""
    algos: list[str] = field(default_factory=lambda: ["stepnft", "ppo", "grpo"])
    """Variants to compare (space- or comma-separated), from the list above."""
    seeds: list[int] = field(default_factory=lambda: [0])
    """One SFT policy per seed (demonstrations and initial states seeded by it); every variant
    runs once per seed from it."""
    tasks: list[str] | None = None
    """Tasks (space- or comma-separated); None: the base config's."""
    env_steps: int | None = None
    """RL env-step budget of every run (None: the base config's env_step_budget)."""
    jobs: int = 0
    """Runs at once, one subprocess each (0: one per CPU core)."""
    out: str = "runs/compare"
    """Comparison folder; rerun the same command on it to resume."""
    reference: str = "stepnft"
    """Variant the paired differences are taken against (if compared; else the first)."""
    eval_episodes: int | None = None
    """Evaluation episodes per task before and after RL (None: the base config's)."""
    suites: list[str] = field(default_factory=list)
    """Also evaluate every final policy and every SFT start on these suites (ind, vision,
    semantic, execution; space- or comma-separated): the table of IND / OOD success
    (OUT/suites.md). Empty: no suite evaluation."""
    suite_episodes: int = 50
    """Episodes per task and suite for --suites."""

    def __post_init__(self) -> None:
        self.algos = list(dict.fromkeys(a.strip() for item in self.algos for a in item.split(",") if a.strip()))
        if isinstance(self.tasks, list):
            self.tasks = [t.strip() for item in self.tasks for t in item.split(",") if t.strip()]
        unknown = [a for a in self.algos if a not in VARIANTS]
        if not self.algos or unknown:
            raise ValueError(f"--algos {','.join(unknown) or '(none)'}: choose from {', '.join(VARIANTS)}")
        if not self.seeds or any(s < 0 for s in self.seeds) or len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"--seeds must be distinct integers >= 0, got {self.seeds}")
        if self.jobs < 0 or (self.env_steps is not None and self.env_steps < 1):
            raise ValueError(f"--jobs must be >= 0 and --env-steps >= 1, got {self.jobs}, {self.env_steps}")
        if self.eval_episodes is not None and self.eval_episodes < 1:
            raise ValueError(f"--eval-episodes must be >= 1, got {self.eval_episodes}")
        self.suites = [x.strip() for item in self.suites for x in item.split(",") if x.strip()]
        if self.suites:
            from stepnft.suites import check_suites

            check_suites(self.suites)
        if self.suite_episodes < 1:
            raise ValueError(f"--suite-episodes must be >= 1, got {self.suite_episodes}")


def help_text() -> str:
    return f"{' '.join((CompareCommand.__doc__ or '').split())}\n\nvariants (--algos):\n{describe_variants()}\n"


# --- what runs ----------------------------------------------------------------------------------
@dataclass
class Job:
    """One subprocess: the SFT of a seed or a variant's RL run."""

    name: str
    """``sft_seedS``, ``VARIANT_seedS`` or ``suites_ROW_seedS``: its config, log and status key."""
    kind: str
    """``sft``, ``train`` or ``eval`` (the suites of a finished policy)."""
    run_dir: Path
    config: object
    """The TrainConfig it starts from."""


def plan(cmd: CompareCommand) -> tuple[list[Job], list[Job], Path]:
    """Check the settings and build the jobs: ``(SFT jobs, RL jobs, comparison folder)``; with
    ``--suites``, each SFT and RL job is followed by the suite evaluation of its policy."""
    from stepnft.config import load_config, to_dict
    from stepnft.envs import get_simulator
    from stepnft.runs import prepare_run_dir

    base = load_config(cmd.config)
    tasks = cmd.tasks or base.env.tasks
    get_simulator(base.env.name).validate_tasks(tasks)
    budget = cmd.env_steps if cmd.env_steps is not None else base.env_step_budget
    if budget is None:
        raise ValueError("a comparison needs one env-step budget: pass --env-steps N (or set env_step_budget in --config)")
    # The budget ends every run: enough iterations that it always binds (an episode costs >= 1
    # env step), π-StepNFT's EMA schedule staying on the base config's iterations.
    ema_horizon = base.iterations
    base = dataclasses.replace(
        base, env=dataclasses.replace(base.env, tasks=list(tasks)), env_step_budget=budget, num_threads=1, init=None,
        iterations=max(base.iterations, math.ceil(budget / base.episodes_per_iteration)),
        eval=dataclasses.replace(base.eval, episodes=cmd.eval_episodes or base.eval.episodes))
    # As given (relative to the working directory, as every run's --run-dir): the saved configs
    # then move with the folder.
    out = prepare_run_dir(cmd.out)
    settings = to_dict(base)
    for per_run in ("run_dir", "seed", "init"):
        settings.pop(per_run)
    settings["demos"] = {k: v for k, v in settings["demos"].items() if k not in ("path", "seed")}
    _check_same_settings(out / "compare.json", settings)

    sft_jobs, run_jobs = [], []
    for seed in cmd.seeds:
        sft_dir = out / "sft" / f"seed{seed}"
        demos = dataclasses.replace(base.demos, seed=seed, path=str(out / "demos" / f"seed{seed}"))
        sft_cfg = dataclasses.replace(base, seed=seed, run_dir=str(sft_dir), demos=demos)
        sft_jobs.append(Job(f"sft_seed{seed}", "sft", sft_dir, sft_cfg))
        for name in cmd.algos:
            algo = variant_config(name, base.algo)
            if getattr(algo, "ema_horizon", 0) is None:
                algo = dataclasses.replace(algo, ema_horizon=ema_horizon)
            run_dir = out / "runs" / name / f"seed{seed}"
            cfg = dataclasses.replace(sft_cfg, run_dir=str(run_dir), init=str(sft_dir / "policy"), algo=algo)
            run_jobs.append(Job(f"{name}_seed{seed}", "train", run_dir, cfg))
    return sft_jobs, run_jobs, out


def suite_job(cmd: CompareCommand, job: Job, out: Path) -> Job:
    """The suite evaluation of ``job``'s final policy (``stepnft eval --suite ...``)."""
    row = SFT if job.kind == "sft" else job.name.rsplit("_seed", 1)[0]
    run_dir = out / "suites" / row / f"seed{job.config.seed}"
    argv = ["eval", "--policy", str(job.run_dir / "policy"), "--suite", *cmd.suites,
            "--eval.episodes", str(cmd.suite_episodes), "--eval.seed", str(job.config.eval.seed),
            "--out", str(run_dir / "suites.json"), *env_flags(job.config.env),
            *(["--device", job.config.device] if job.config.device != "cpu" else [])]
    return Job(f"suites_{row}_seed{job.config.seed}", "eval", run_dir, argv)


def env_flags(env) -> list[str]:
    """Command-line flags that rebuild ``env`` (fields left at their defaults are omitted)."""
    default = type(env)()
    flags = []
    for f in dataclasses.fields(env):
        value = getattr(env, f.name)
        if value == getattr(default, f.name):
            continue
        flag = "--env." + f.name.replace("_", "-")
        if isinstance(value, bool):
            flags.append(flag if value else "--env.no-" + f.name.replace("_", "-"))
        elif isinstance(value, (list, tuple)):
            flags += [flag, *map(str, value)] if value else []
        else:
            flags += [flag, str(value)]
    return flags


def _flat(tree: dict, prefix: str = "") -> dict:
    flat = {}
    for k, v in tree.items():
        flat |= _flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v}
    return flat


def _check_same_settings(path: Path, settings: dict) -> None:
    """Record the comparison's settings, or check a rerun asks for the same ones."""
    from stepnft.runs import write_atomic

    settings = json.loads(json.dumps(settings))  # tuples as lists, as they come back from disk
    if not path.is_file():
        write_atomic(path, json.dumps(settings, indent=2))
        return
    old, new = _flat(json.loads(path.read_text())), _flat(settings)
    diff = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
    if diff:
        raise ValueError(f"{path.parent} holds a comparison with other settings (differs in: {', '.join(diff)}): "
                         "rerun it with its own --config and flags (algorithms and seeds may be added), or choose "
                         "another --out")


# --- running ------------------------------------------------------------------------------------
def job_state(job: Job) -> str:
    """``finished``, ``resumable`` (a checkpoint to continue from) or ``fresh``."""
    if job.kind == "eval":
        return "finished" if (job.run_dir / "suites.json").is_file() else "fresh"
    if job.kind == "sft":
        return "finished" if (job.run_dir / "summary.json").is_file() and (job.run_dir / "policy").is_dir() else "fresh"
    if (job.run_dir / "summary.json").is_file():
        return "finished"
    return "resumable" if (job.run_dir / "checkpoints" / "LATEST").is_file() else "fresh"


class JobRunner:
    """Runs jobs as subprocesses (from worker threads) and stops them all on an interrupt."""

    def __init__(self, out: Path):
        self.out = out
        self.procs: set[subprocess.Popen] = set()
        self.lock = threading.Lock()
        self.stopping = False

    def run(self, job: Job) -> dict:
        """Run (or resume) one job; returns ``{"rc", "wall_clock_s", "skipped"}``."""
        from stepnft.config import save_config

        state = job_state(job)
        if state == "finished":
            return {"rc": 0, "wall_clock_s": 0.0, "skipped": True}
        if job.kind == "eval":
            job.run_dir.mkdir(parents=True, exist_ok=True)
            argv = list(job.config)
        elif state == "resumable":
            argv = [job.kind, "--resume", str(job.run_dir)]
        else:
            if job.run_dir.exists():  # a start that died before its first checkpoint: nothing to keep
                shutil.rmtree(job.run_dir)
            config_path = self.out / "configs" / f"{job.name}.yaml"
            config_path.parent.mkdir(exist_ok=True)
            save_config(job.config, config_path)
            argv = [job.kind, "--config", str(config_path)]
        log_path = self.out / "logs" / f"{job.name}.log"
        log_path.parent.mkdir(exist_ok=True)
        # One torch thread per run; the children import the same stepnft as this process.
        package_root = str(Path(__file__).resolve().parents[1])
        env = os.environ | {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "TQDM_MININTERVAL": "30",
                            "PYTHONPATH": os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")]))}
        start = time.perf_counter()
        with log_path.open("a") as f:
            f.write(f"\n=== {time.strftime('%Y-%m-%d %H:%M:%S')} stepnft {' '.join(argv)}\n")
            f.flush()
            with self.lock:
                if self.stopping:
                    return {"rc": None, "wall_clock_s": 0.0, "skipped": True}
                proc = subprocess.Popen([sys.executable, "-m", "stepnft.cli", *argv], stdout=f,
                                        stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
                self.procs.add(proc)
            rc = proc.wait()
            with self.lock:
                self.procs.discard(proc)
        return {"rc": rc, "wall_clock_s": time.perf_counter() - start, "skipped": False}

    def stop(self) -> None:
        """Start nothing more and end the running children (their last checkpoints stay intact)."""
        with self.lock:
            self.stopping = True
            for proc in self.procs:
                proc.terminate()


def run_compare(cmd: CompareCommand, log: Callable[[str], None] = print) -> int:
    """Run (or resume) the comparison and write its report; 0 if every run finished, else 1
    (130 when interrupted by Ctrl-C or SIGTERM)."""
    from stepnft.runs import write_atomic

    sft_jobs, run_jobs, out = plan(cmd)
    suite_jobs = {j.name: suite_job(cmd, j, out) for j in sft_jobs + run_jobs} if cmd.suites else {}
    status_path = out / "status.json"
    status = json.loads(status_path.read_text()) if status_path.is_file() else {}
    jobs = cmd.jobs or os.cpu_count() or 1
    runs_of_seed = {sft.name: [j for j in run_jobs if j.config.seed == sft.config.seed] for sft in sft_jobs}
    total = len(sft_jobs) + len(run_jobs) + len(suite_jobs)
    log(f"comparing {', '.join(cmd.algos)} on {len(cmd.seeds)} seed(s): {total} jobs ({len(sft_jobs)} SFT), "
        f"{jobs} at once, in {out}")
    completed = 0

    def record(job: Job, result: dict) -> None:
        nonlocal completed
        completed += 1
        entry = status.get(job.name, {"wall_clock_s": 0.0, "attempts": 0})
        if not result["skipped"]:
            entry["wall_clock_s"] += result["wall_clock_s"]
            entry["attempts"] += 1
        interrupted = result["rc"] in (130, -signal.SIGINT, -signal.SIGTERM)
        entry |= {"rc": result["rc"], "state": job_state(job) if result["rc"] == 0 else
                  "interrupted" if interrupted else "crashed",
                  "log": str(Path("logs") / f"{job.name}.log")}
        status[job.name] = entry
        write_atomic(status_path, json.dumps(status, indent=2))
        if interrupted:
            verb = "interrupted (a rerun resumes it)"
        elif result["rc"] != 0:
            why = "its seed's SFT failed" if result["rc"] is None else f"exit code {result['rc']}; see {out / entry['log']}"
            verb = f"CRASHED ({why})"
        else:
            verb = "kept (finished earlier)" if result["skipped"] else f"finished in {result['wall_clock_s'] / 60:.1f} min"
        log(f"[{completed}/{total}] {job.name}: {verb}")

    runner = JobRunner(out)
    pool = ThreadPoolExecutor(max_workers=jobs)
    pending: dict[Future, Job] = {}
    in_main = threading.current_thread() is threading.main_thread()
    previous_sigterm = signal.signal(signal.SIGTERM, signal.default_int_handler) if in_main else None  # as Ctrl-C
    try:
        for job in sft_jobs:
            pending[pool.submit(runner.run, job)] = job
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                job = pending.pop(future)
                result = future.result()
                record(job, result)
                follow = runs_of_seed.get(job.name, []) + ([suite_jobs[job.name]] if job.name in suite_jobs else [])
                for run in follow:
                    if result["rc"] == 0:
                        pending[pool.submit(runner.run, run)] = run
                    else:
                        record(run, {"rc": None, "wall_clock_s": 0.0, "skipped": True})
    except KeyboardInterrupt:
        runner.stop()
        pool.shutdown(wait=True, cancel_futures=True)
        for future, job in pending.items():  # the runs just stopped: their time counts
            if not future.cancelled() and not future.result()["skipped"]:
                record(job, future.result())
        write_report(cmd, out, status)
        log("interrupted: rerun the same command to resume (finished runs are kept, the others continue from "
            "their last checkpoint)")
        return 130
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous_sigterm)
    pool.shutdown()
    write_report(cmd, out, status)
    log(f"wrote {out / 'comparison.md'}, comparison.csv, comparison.png" + (", suites.md" if cmd.suites else ""))
    everything = sft_jobs + run_jobs + list(suite_jobs.values())
    return 0 if all(status.get(j.name, {}).get("state") == "finished" for j in everything) else 1


# --- the report ---------------------------------------------------------------------------------
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


def load_result(run_dir: Path) -> dict | None:
    """A finished run's after-RL success per task (and ``average``), env steps, evaluation curve
    ``[(env_steps, success)]`` and learner samples/s; None if it did not finish."""
    from stepnft.runs import read_metrics

    if not (run_dir / "summary.json").is_file():
        return None
    summary = json.loads((run_dir / "summary.json").read_text())
    records = read_metrics(run_dir / "metrics.jsonl")
    update_s = sum(r.get("time/update_s") or 0.0 for r in records)
    samples = sum(r.get("charts/samples") or 0 for r in records)
    return {"success": {t: v["after"]["success"] for t, v in summary["tasks"].items()} | {
                "average": summary["average"]["after"]},
            "env_steps": summary["env_steps"],
            # Test states before and after, validation states during training.
            "curve": [(r["env_steps"], r.get("charts/validation_success_rate", r.get("charts/success_rate")))
                      for r in records if not r.get("final") and
                      r.get("charts/validation_success_rate", r.get("charts/success_rate")) is not None]
                     + [(summary["env_steps"], summary["average"]["after"])],
            "samples_per_s": samples / update_s if update_s > 0 else math.nan}


def load_sft(run_dir: Path) -> dict | None:
    path = run_dir / "summary.json"
    if not path.is_file():
        return None
    result = json.loads(path.read_text())["sft"]
    return {"success": {t: v["success"] for t, v in result["tasks"].items()} | {"average": result["average"]}}


def summarise(cmd: CompareCommand, out: Path, status: dict) -> dict:
    """Per row (SFT, then each variant): per-seed results, success and paired-difference
    statistics per task and on average, run counts, means of env steps, wall-clock and speed."""
    tasks = json.loads((out / "compare.json").read_text())["env"]["tasks"]
    columns = [*tasks, "average"]
    reference = cmd.reference if cmd.reference in cmd.algos else cmd.algos[0]
    per_seed = {SFT: {s: load_sft(out / "sft" / f"seed{s}") for s in cmd.seeds}}
    per_seed |= {a: {s: load_result(out / "runs" / a / f"seed{s}") for s in cmd.seeds} for a in cmd.algos}
    rows = {}
    for name, results in per_seed.items():
        done = {s: r for s, r in results.items() if r is not None}
        ref = per_seed[reference]
        paired = [s for s in done if ref.get(s) is not None] if name not in (SFT, reference) else []
        diff = {c: [done[s]["success"][c] - ref[s]["success"][c] for s in paired] for c in columns}
        names = [f"{SFT}_seed{s}" if name == SFT else f"{name}_seed{s}" for s in cmd.seeds]
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
            "curves": {s: r.get("curve") for s, r in done.items()},
        }
    return {"tasks": tasks, "columns": columns, "reference": reference, "rows": rows}


def _mean(values: list) -> float:
    values = [v for v in values if v is not None and not math.isnan(v)]
    return statistics.fmean(values) if values else math.nan


def format_ci(stats: tuple[float, float, float], signed: bool = False) -> str:
    """``mean [lo, hi]`` of :func:`mean_ci`'s triple (``–`` without a mean, no interval without one)."""
    mean, lo, hi = stats
    if math.isnan(mean):
        return "–"
    fmt = "{:+.2f}" if signed else "{:.2f}"
    return fmt.format(mean) + ("" if math.isnan(lo) else f" [{fmt.format(lo)}, {fmt.format(hi)}]")


def command_line(cmd: CompareCommand) -> str:
    tasks = f" --tasks {' '.join(cmd.tasks)}" if cmd.tasks else ""
    steps = f" --env-steps {cmd.env_steps}" if cmd.env_steps is not None else ""
    evals = f" --eval-episodes {cmd.eval_episodes}" if cmd.eval_episodes is not None else ""
    suites = f" --suites {','.join(cmd.suites)} --suite-episodes {cmd.suite_episodes}" if cmd.suites else ""
    return (f"stepnft compare --config {cmd.config} --algos {','.join(cmd.algos)} "
            f"--seeds {' '.join(map(str, cmd.seeds))}{tasks}{steps}{evals}{suites} --out {cmd.out}")


def write_report(cmd: CompareCommand, out: Path, status: dict) -> dict:
    """``comparison.md``, ``comparison.csv`` and ``comparison.png`` from whatever has finished."""
    from stepnft.runs import write_atomic

    summary = summarise(cmd, out, status)
    settings = json.loads((out / "compare.json").read_text())
    columns, ref, rows = summary["columns"], summary["reference"], summary["rows"]

    lines = [f"# Comparison: {', '.join(cmd.algos)}", "", f"    {command_line(cmd)}", "",
             f"RL budget {settings['env_step_budget']:,} env steps per run; seeds {', '.join(map(str, cmd.seeds))}; "
             f"ODE evaluation on {settings['eval']['episodes']} fixed initial states per task. Success: mean over "
             "seeds [95 % t-interval over seeds]. Δ: paired difference to "
             f"`{ref}` from the same SFT policy per seed, on average over every (seed, task) pair [95 % t-interval].",
             "", "| algorithm | runs | " + " | ".join(columns) + f" | Δ vs {ref} | env steps | wall-clock (min) | "
             "learner samples/s |", "|---" * (len(columns) + 6) + "|"]
    for name, row in rows.items():
        runs = f"{row['finished']}/{row['runs']}" + (f" ({len(row['crashed'])} crashed)" if row["crashed"] else "")
        label = "SFT (start)" if name == SFT else name
        delta = format_ci(row["diff"]["average"], signed=True) if row["paired_seeds"] else "–"
        extra = "– | – | –" if name == SFT else (
            f"{row['env_steps']:,.0f} | {row['wall_clock_s'] / 60:.1f} | {row['samples_per_s']:,.0f}"
            if row["finished"] else "– | – | –")
        lines.append(f"| {label} | {runs} | " + " | ".join(format_ci(row["success"][c]) for c in columns)
                     + f" | {delta} | {extra} |")
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
    lines += ["", "Learner samples/s: recorded denoising transitions per second of update time. Wall-clock: the "
              "run's own time (runs shared the machine with the other jobs).", "",
              "![success against env steps](comparison.png)", ""]
    write_atomic(out / "comparison.md", "\n".join(lines))

    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["algorithm", "task", "runs", "finished", "crashed", "success_mean", "success_ci_lo",
                     "success_ci_hi", f"diff_vs_{ref}_mean", "diff_ci_lo", "diff_ci_hi", "paired_seeds",
                     "env_steps_mean", "wall_clock_s_mean", "learner_samples_per_s"])
    for name, row in rows.items():
        for c in columns:
            diff = row["diff"][c] if row["paired_seeds"] else (math.nan,) * 3
            numbers = [*row["success"][c], *diff, row["paired_seeds"], row["env_steps"], row["wall_clock_s"],
                       row["samples_per_s"]]
            writer.writerow([name, c, row["runs"], row["finished"], len(row["crashed"]),
                             *("" if isinstance(x, float) and math.isnan(x) else round(x, 4) for x in numbers)])
    write_atomic(out / "comparison.csv", buffer.getvalue())
    plot_comparison(summary, settings["env_step_budget"], out / "comparison.png")
    if cmd.suites:
        write_suites_report(cmd, out, summary["reference"])
    return summary


def write_suites_report(cmd: CompareCommand, out: Path, reference: str) -> dict:
    """``suites.md``: success per suite and the OOD average (mean [95 % t-interval] over seeds)
    per algorithm, and the paired OOD difference to the reference (the paper's table shape)."""
    from stepnft.runs import write_atomic
    from stepnft.suites import SUITE_NAMES, summarize_suites

    columns = [*SUITE_NAMES, "ood_average"]
    table = {}
    for row in [SFT, *cmd.algos]:
        per_seed = {}
        for seed in cmd.seeds:
            path = out / "suites" / row / f"seed{seed}" / "suites.json"
            if path.is_file():
                data = json.loads(path.read_text())  # one suite's result, or several under "suites"
                per_seed[seed] = summarize_suites(data["suites"] if "suites" in data else {data["suite"]: data})
        table[row] = per_seed
    lines = [f"# Suites: {', '.join(cmd.suites)}", "", f"    {command_line(cmd)}", "",
             f"ODE evaluation of each final policy (and each SFT start), {cmd.suite_episodes} episodes per task and "
             "suite; mean over seeds [95 % t-interval]. OOD average: the mean of the vision, semantic and execution "
             f"suites that apply. Δ OOD: paired difference to `{reference}`.", "",
             "| algorithm | seeds | " + " | ".join(columns) + f" | Δ OOD vs {reference} |", "|---" * (len(columns) + 3) + "|"]
    for row, per_seed in table.items():
        cells = [format_ci(mean_ci([r[c] for r in per_seed.values() if r[c] is not None], 0.0, 1.0)) for c in columns]
        ref = table.get(reference, {})
        paired = [per_seed[s]["ood_average"] - ref[s]["ood_average"] for s in per_seed
                  if s in ref and row != reference and per_seed[s]["ood_average"] is not None
                  and ref[s]["ood_average"] is not None]
        delta = format_ci(mean_ci(paired, -1.0, 1.0), signed=True) if paired else "–"
        lines.append(f"| {'SFT (start)' if row == SFT else row} | {len(per_seed)} | " + " | ".join(cells) + f" | {delta} |")
    write_atomic(out / "suites.md", "\n".join(lines) + "\n")
    return table


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
