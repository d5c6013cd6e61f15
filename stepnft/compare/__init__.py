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

One module per job: ``command`` (the flags), ``plan`` (the run configs and jobs, the settings
check), ``schedule`` (subprocesses, the thread pool, signals, status and resume), ``stats``
(results, CIs, paired differences), ``report`` (markdown, CSV, plot); :func:`run_compare`
composes them.
"""

from __future__ import annotations

import os
from typing import Callable

from stepnft.compare.command import CompareCommand, command_line, help_text
from stepnft.compare.plan import SFT, Job, comparison_config, env_flags, plan, suite_job
from stepnft.compare.report import plot_comparison, write_report, write_suites_report
from stepnft.compare.schedule import JobRunner, StatusFile, job_state, schedule, sigterm_as_interrupt
from stepnft.runs import writer_lock
from stepnft.compare.stats import T_975, load_result, load_sft, mean_ci, paired_differences, summarise, t_quantile
from stepnft.evaluate import format_ci

__all__ = ["SFT", "T_975", "CompareCommand", "Job", "JobRunner", "StatusFile", "command_line", "comparison_config",
           "env_flags", "format_ci", "help_text", "job_state", "load_result", "load_sft", "mean_ci",
           "paired_differences", "plan", "plot_comparison", "run_compare", "schedule", "sigterm_as_interrupt",
           "suite_job", "summarise", "t_quantile", "write_report", "write_suites_report"]


def run_compare(cmd: CompareCommand, log: Callable[[str], None] = print) -> int:
    """Run (or resume) the comparison and write its report; 0 if every run finished, else 1
    (130 when interrupted by Ctrl-C or SIGTERM)."""
    with writer_lock(cmd.out):  # one comparison writes OUT (its runs lock their own folders)
        return _run_compare(cmd, log)


def _run_compare(cmd: CompareCommand, log: Callable[[str], None]) -> int:
    sft_jobs, run_jobs, out = plan(cmd)
    suite_jobs = {j.name: suite_job(cmd, j, out) for j in sft_jobs + run_jobs} if cmd.suites else {}
    # Each SFT is followed by its seed's runs, and each policy by its suite evaluation.
    then = {sft.name: [j for j in run_jobs if j.config.seed == sft.config.seed] for sft in sft_jobs}
    for name, job in suite_jobs.items():
        then.setdefault(name, []).append(job)
    everything = sft_jobs + run_jobs + list(suite_jobs.values())
    workers = cmd.jobs or os.cpu_count() or 1
    status = StatusFile(out / "status.json", len(everything), log)
    log(f"comparing {', '.join(cmd.algos)} on {len(cmd.seeds)} seed(s): {len(everything)} jobs ({len(sft_jobs)} SFT), "
        f"{workers} at once, in {out}")
    runner = JobRunner(out)
    try:
        with sigterm_as_interrupt():
            schedule(runner.run, runner.stop, sft_jobs, then, workers, status.record)
    except KeyboardInterrupt:
        write_report(cmd, out, status.entries)
        log("interrupted: rerun the same command to resume (finished runs are kept, the others continue from "
            "their last checkpoint)")
        return 130
    write_report(cmd, out, status.entries)
    log(f"wrote {out / 'comparison.md'}, comparison.csv, comparison.png" + (", suites.md" if cmd.suites else ""))
    return 0 if status.finished(everything) else 1
