"""Running a comparison's jobs: each a ``stepnft`` subprocess with one torch thread
(:class:`JobRunner`), ``--jobs`` at once on a thread pool, each SFT's runs started once it
finished (:func:`schedule`), their progress in ``OUT/status.json`` (:class:`StatusFile`), and
what a rerun resumes (:func:`job_state`). The pool is shut down and every child ended on every
way out: success, an error, Ctrl-C or SIGTERM (:func:`sigterm_as_interrupt`)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from pathlib import Path

from stepnft.compare.plan import Job
from stepnft.config import save_config
from stepnft.runs import write_atomic

NOT_RUN = {"rc": None, "wall_clock_s": 0.0, "skipped": True}
"""The result of a job that did not start: the job it follows (its seed's SFT, or the run whose
policy it evaluates) did not finish, or the comparison stopped."""


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
        self.command = [sys.executable, "-m", "stepnft.cli"]
        """The program a job's arguments are given to."""
        self.procs: set[subprocess.Popen] = set()
        self.lock = threading.Lock()
        self.stopping = False

    def run(self, job: Job) -> dict:
        """Run (or resume) one job; returns ``{"rc", "wall_clock_s", "skipped"}``."""
        state = job_state(job)
        if state == "finished":
            return {"rc": 0, "wall_clock_s": 0.0, "skipped": True}
        argv = self.arguments(job, state)
        log_path = self.out / "logs" / f"{job.name}.log"
        log_path.parent.mkdir(exist_ok=True)
        # One torch thread per run; the children import the same stepnft as this process.
        package_root = str(Path(__file__).resolve().parents[2])
        env = os.environ | {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "TQDM_MININTERVAL": "30",
                            "PYTHONPATH": os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")]))}
        start = time.perf_counter()
        with log_path.open("a") as f:
            f.write(f"\n=== {time.strftime('%Y-%m-%d %H:%M:%S')} stepnft {' '.join(argv)}\n")
            f.flush()
            with self.lock:
                if self.stopping:
                    return dict(NOT_RUN)
                proc = subprocess.Popen([*self.command, *argv], stdout=f,
                                        stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
                self.procs.add(proc)
            rc = proc.wait()
            with self.lock:
                self.procs.discard(proc)
        return {"rc": rc, "wall_clock_s": time.perf_counter() - start, "skipped": False}

    def arguments(self, job: Job, state: str) -> list[str]:
        """The ``stepnft`` arguments that start (``fresh``) or resume ``job``."""
        if job.kind == "eval":
            job.run_dir.mkdir(parents=True, exist_ok=True)
            return list(job.config)
        if state == "resumable":
            return [job.kind, "--resume", str(job.run_dir)]
        if job.run_dir.exists():  # a start that died before its first checkpoint: nothing to keep
            shutil.rmtree(job.run_dir)
        config_path = self.out / "configs" / f"{job.name}.yaml"
        config_path.parent.mkdir(exist_ok=True)
        save_config(job.config, config_path)
        return [job.kind, "--config", str(config_path)]

    def stop(self) -> None:
        """Start nothing more and end the running children (their last checkpoints stay intact)."""
        with self.lock:
            self.stopping = True
            for proc in self.procs:
                proc.terminate()


class StatusFile:
    """``OUT/status.json``, per job: state, exit code, attempts, wall-clock and log; a rerun
    adds to it. Each :meth:`record` also logs one progress line."""

    def __init__(self, path: Path, total: int, log: Callable[[str], None] = print):
        self.path, self.total, self.log = path, total, log
        self.entries: dict[str, dict] = json.loads(path.read_text()) if path.is_file() else {}
        self.completed = 0

    def record(self, job: Job, result: dict) -> None:
        """Record ``job``'s result (:meth:`JobRunner.run`'s, or :data:`NOT_RUN`)."""
        self.completed += 1
        entry = self.entries.get(job.name, {"wall_clock_s": 0.0, "attempts": 0})
        if not result["skipped"]:
            entry["wall_clock_s"] += result["wall_clock_s"]
            entry["attempts"] += 1
        interrupted = result["rc"] in (130, -signal.SIGINT, -signal.SIGTERM)
        not_run = result["rc"] is None
        entry |= {"rc": result["rc"], "state": job_state(job) if result["rc"] == 0 else
                  "interrupted" if interrupted else "not run" if not_run else "crashed",
                  "log": str(Path("logs") / f"{job.name}.log")}
        self.entries[job.name] = entry
        write_atomic(self.path, json.dumps(self.entries, indent=2))
        if interrupted:
            verb = "interrupted (a rerun resumes it)"
        elif not_run:
            verb = "not run: the job it follows did not finish (a rerun starts it once that one has)"
        elif result["rc"] != 0:
            verb = f"CRASHED (exit code {result['rc']}; see {self.path.parent / entry['log']})"
        else:
            verb = "kept (finished earlier)" if result["skipped"] else f"finished in {result['wall_clock_s'] / 60:.1f} min"
        self.log(f"[{self.completed}/{self.total}] {job.name}: {verb}")

    def finished(self, jobs: list[Job]) -> bool:
        return all(self.entries.get(j.name, {}).get("state") == "finished" for j in jobs)


def schedule(run: Callable[[Job], dict], stop: Callable[[], None], first: list[Job], then: dict[str, list[Job]],
             workers: int, record: Callable[[Job, dict], None]) -> None:
    """Run ``first`` on ``workers`` threads, and the jobs ``then[job.name]`` once ``job`` succeeded
    (recorded as :data:`NOT_RUN` when it failed); ``record(job, result)`` as each ends, in this
    thread. A free thread takes a waiting ``eval`` job before any other (in order otherwise):
    a finished run's suites take minutes and complete its results, rather than waiting behind
    every run not yet started. On any exception (KeyboardInterrupt too) ``stop()`` ends the
    running jobs, whose results are recorded, and the exception propagates; the pool is shut
    down on every exit."""
    pool = ThreadPoolExecutor(max_workers=workers)
    pending: dict[Future, Job] = {}
    waiting = list(first)

    def start_free() -> None:
        while waiting and len(pending) < workers:
            job = next((j for j in waiting if j.kind == "eval"), waiting[0])
            waiting.remove(job)
            pending[pool.submit(run, job)] = job

    try:
        start_free()
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                job = pending.pop(future)
                result = future.result()
                record(job, result)
                for follower in then.get(job.name, []):
                    if result["rc"] == 0:
                        waiting.append(follower)
                    else:
                        record(follower, NOT_RUN)
            start_free()
    except BaseException:
        stop()
        pool.shutdown(wait=True, cancel_futures=True)
        for future, job in pending.items():  # the runs just stopped: their time counts
            if not future.cancelled() and future.exception() is None and not future.result()["skipped"]:
                record(job, future.result())
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block SIGTERM raises KeyboardInterrupt, as Ctrl-C does (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
