"""Where rollouts go: equal and informative splits of an iteration's episodes."""

import numpy as np
import torch

from stepnft.rollout.allocation import TaskAllocator


def test_equal_allocation_leaves_the_waves_alone():
    assert TaskAllocator(3).allocate(40) is None
    np.testing.assert_allclose(TaskAllocator(4).shares(), 0.25)


def test_informative_allocation_favours_tasks_near_half_and_keeps_a_floor():
    alloc = TaskAllocator(3, "informative", floor=0.3, initial_success=[0.5, 1.0, 0.1])
    counts = alloc.allocate(80)
    assert sum(counts) == 80 and counts[0] > counts[2] > counts[1] >= 80 * 0.3 / 3 - 1
    np.testing.assert_allclose(alloc.shares().sum(), 1.0)
    grouped = alloc.allocate(80, multiple=4)
    assert all(c % 4 == 0 and c >= 4 for c in grouped) and sum(grouped) == 80


def test_estimates_follow_the_rollouts_and_round_trip():
    alloc = TaskAllocator(2, "informative", smoothing=0.5, initial_success=[0.0, 0.0])

    class Played:
        episode_task = torch.tensor([0, 0, 0, 0])
        episode_success = torch.tensor([True, True, False, True])

    alloc.update(Played())
    np.testing.assert_allclose(alloc.success, [0.375, 0.0])  # task 1 did not play: unchanged
    again = TaskAllocator(2, "informative")
    again.load_state_dict(alloc.state_dict())
    np.testing.assert_allclose(again.success, alloc.success)
