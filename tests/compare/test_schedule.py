"""The comparison's scheduler: follow-up jobs, and no thread or child process left behind on
any way out (success, an error in a job, Ctrl-C, SIGTERM)."""

import json
import os
import signal
import sys
import threading
import time

import pytest

from stepnft.compare.plan import Job
from stepnft.compare.schedule import NOT_RUN, JobRunner, StatusFile, schedule, sigterm_as_interrupt

SLEEPER = [sys.executable, "-c", "import time; time.sleep(120)"]
"""A child that runs until it is ended: stands for a training run."""


def eval_job(root, name):
    return Job(name, "eval", root / name, ["unused"])


def pool_threads():
    return [t for t in threading.enumerate() if t.name.startswith("ThreadPoolExecutor")]


def wait_for_child(runner, timeout=30.0):
    end = time.monotonic() + timeout
    while not runner.procs:
        assert time.monotonic() < end, "the child never started"
        time.sleep(0.01)


def test_followers_run_after_success_and_are_skipped_after_failure(tmp_path):
    ran, recorded = [], {}

    def run(job):
        ran.append(job.name)
        return {"rc": 0 if job.name != "sft_seed1" else 2, "wall_clock_s": 1.0, "skipped": False}

    first = [eval_job(tmp_path, "sft_seed0"), eval_job(tmp_path, "sft_seed1")]
    then = {"sft_seed0": [eval_job(tmp_path, "a_seed0")], "sft_seed1": [eval_job(tmp_path, "a_seed1")]}
    schedule(run, lambda: None, first, then, 2, lambda job, result: recorded.setdefault(job.name, result))
    assert sorted(ran) == ["a_seed0", "sft_seed0", "sft_seed1"]
    assert recorded["a_seed1"] == NOT_RUN and recorded["a_seed0"]["rc"] == 0
    assert not pool_threads()


def test_an_error_in_one_job_ends_the_others_and_leaves_nothing_running(tmp_path):
    runner = JobRunner(tmp_path)
    runner.command = SLEEPER
    recorded = {}

    def run(job):
        if job.name == "broken":
            wait_for_child(runner)
            raise OSError("disk full")
        return runner.run(job)

    jobs = [eval_job(tmp_path, "slow"), eval_job(tmp_path, "broken")]
    with pytest.raises(OSError, match="disk full"):
        schedule(run, runner.stop, jobs, {}, 2, lambda job, result: recorded.setdefault(job.name, result))
    assert not pool_threads()
    assert runner.stopping and not runner.procs  # the child was ended and waited for
    assert recorded["slow"]["rc"] == -signal.SIGTERM and not recorded["slow"]["skipped"]  # its time counts
    assert runner.run(eval_job(tmp_path, "late")) == NOT_RUN  # nothing starts after a stop


@pytest.fixture
def ctrl_c_interrupts():
    """Ctrl-C as in a terminal: a process a shell starts in the background (`cmd &`, as a CI
    script may) inherits SIGINT ignored, and Python then raises nothing on it."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupt_ends_every_child_and_the_pool(tmp_path, signum, ctrl_c_interrupts):
    runner = JobRunner(tmp_path)
    runner.command = SLEEPER
    status = StatusFile(tmp_path / "status.json", 3, log=lambda line: None)
    jobs = [eval_job(tmp_path, f"slow{k}") for k in range(3)]  # two run, one waits for a worker
    sender = threading.Thread(target=lambda: (wait_for_child(runner), time.sleep(0.2), os.kill(os.getpid(), signum)))
    previous = signal.getsignal(signal.SIGTERM)
    sender.start()
    with pytest.raises(KeyboardInterrupt), sigterm_as_interrupt():
        schedule(runner.run, runner.stop, jobs, {}, 2, status.record)
    sender.join()
    assert signal.getsignal(signal.SIGTERM) is previous
    assert not pool_threads() and not runner.procs
    entries = json.loads((tmp_path / "status.json").read_text())
    assert {e["state"] for e in entries.values()} == {"interrupted"} and len(entries) == 2  # slow2 never started


def test_a_job_whose_predecessor_did_not_finish_is_recorded_as_not_run_not_as_crashed(tmp_path):
    lines = []
    status = StatusFile(tmp_path / "status.json", 3, lines.append)
    status.record(eval_job(tmp_path, "ppo_seed0"), {"rc": -signal.SIGTERM, "wall_clock_s": 5.0, "skipped": False})
    status.record(eval_job(tmp_path, "suites_ppo_seed0"), NOT_RUN)
    status.record(eval_job(tmp_path, "grpo_seed0"), {"rc": 2, "wall_clock_s": 1.0, "skipped": False})
    entries = json.loads((tmp_path / "status.json").read_text())
    assert [entries[n]["state"] for n in ("ppo_seed0", "suites_ppo_seed0", "grpo_seed0")] == \
        ["interrupted", "not run", "crashed"]
    assert entries["suites_ppo_seed0"]["attempts"] == 0
    assert "interrupted" in lines[0] and "not run: the job it follows did not finish" in lines[1]
    assert "CRASHED (exit code 2" in lines[2] and "CRASHED" not in lines[1]


def test_a_finished_runs_suites_go_before_the_runs_still_waiting(tmp_path):
    ran = []

    def run(job):
        ran.append(job.name)
        return {"rc": 0, "wall_clock_s": 1.0, "skipped": False}

    train = [Job(f"{v}_seed0", "train", tmp_path / v, None) for v in ("a", "b", "c")]
    then = {"sft_seed0": train, "a_seed0": [eval_job(tmp_path, "suites_a_seed0")],
            "b_seed0": [eval_job(tmp_path, "suites_b_seed0")]}
    schedule(run, lambda: None, [eval_job(tmp_path, "sft_seed0")], then, 1, lambda job, result: None)
    # One thread: a's suites run before b and c, which waited since the SFT finished.
    assert ran == ["sft_seed0", "a_seed0", "suites_a_seed0", "b_seed0", "suites_b_seed0", "c_seed0"]
