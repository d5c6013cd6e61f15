"""benchmarks/cost_growth.py: the memory of a process tree is read from /proc, and the time to a
gain is read from a learning benchmark's validation curve."""

import json
import multiprocessing
import os

import pytest
from benchmark_loader import benchmark_module


@pytest.fixture(scope="module")
def cost_growth():
    with benchmark_module("cost_growth") as module:
        yield module


def _hold(ready, done):
    block = bytearray(64 * 2**20)  # 64 MiB touched: counted in the child's PSS
    block[::4096] = b"x" * len(block[::4096])
    ready.set()
    done.wait(30)


def test_children_and_their_memory_are_found(cost_growth):
    context = multiprocessing.get_context("fork")
    ready, done = context.Event(), context.Event()
    child = context.Process(target=_hold, args=(ready, done))
    child.start()
    try:
        assert ready.wait(30)
        assert child.pid in cost_growth.children(os.getpid())
        assert cost_growth.pss_mb(child.pid) > 60
        assert cost_growth.pss_mb(os.getpid()) > 0
    finally:
        done.set()
        child.join()
    assert child.pid not in cost_growth.children(os.getpid())
    assert cost_growth.pss_mb(child.pid) == 0.0  # gone: nothing, not an error


def test_time_to_a_gain_reads_the_first_validation_at_or_above_it(cost_growth, tmp_path):
    curve = [[0, 0.30], [1000, 0.35], [2000, 0.41], [3000, 0.38], [4000, 0.52]]
    assert cost_growth.first_reaching(curve, 0.40) == 2000
    assert cost_growth.first_reaching(curve, 0.60) is None
    run = {"seed": 0, "commit": "abc", "env_steps": 4000, "wall_clock_s": 7200.0, "algorithm": "stepnft",
           "time_s": {"rollouts": 6000.0, "updates": 600.0, "validation": 600.0},
           "curves": {"charts/validation_success_rate": curve}}
    (tmp_path / "learning.json").write_text(json.dumps({"command": "x", "commit": "abc", "tasks": ["a", "b"], "runs": [run]}))
    row = cost_growth.from_learning("2 tasks", tmp_path)
    seed = row["seeds"][0]
    assert row["tasks"] == 2 and seed["steps_to_plus_0.10"] == 2000 and seed["steps_to_plus_0.20"] == 4000
    assert seed["hours_to_plus_0.10"] == pytest.approx(1.0)  # half the env steps of a 2-hour run
    assert seed["shares"]["updates"] == pytest.approx(600 / 7200) and seed["rollout_steps_per_s"] == pytest.approx(4000 / 6000)
    table = cost_growth.tables([], [row])
    assert "| 2 tasks | 2 | stepnft | 1 |" in table and "(1/1)" in table
