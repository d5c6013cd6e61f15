"""The declared batch: every key checked where it is built."""

import pytest
import torch

from stepnft.batch import Batch


def tiny_batch(episodes=2, calls=3, steps=5, horizon=2, action_dim=2) -> dict:
    chunk = lambda n: torch.zeros(n, horizon, action_dim)  # noqa: E731
    return dict(
        episode_success=torch.tensor([True, False][:episodes]), episode_task=torch.zeros(episodes, dtype=torch.int64),
        episode_length=torch.full((episodes,), 4), episode_seed=torch.full((episodes,), -1),
        obs={"state": torch.zeros(calls, 3), "task": torch.zeros(calls, dtype=torch.int64)},
        actions=chunk(calls), mask=torch.ones(calls, horizon, dtype=torch.bool), reward=torch.zeros(calls),
        done=torch.tensor([False, True, True]), episode=torch.tensor([0, 0, 1]),
        call=torch.tensor([0, 0, 1, 2, 2]), x_t=chunk(steps), x_next=chunk(steps), v_old=chunk(steps),
        t=torch.ones(steps), dt=torch.full((steps,), 0.25),
    )


def test_derived_views_follow_the_links():
    batch = Batch(**tiny_batch())
    assert (batch.num_episodes, batch.num_calls, batch.num_steps, batch.env_steps) == (2, 3, 5, 8)
    assert batch.step_episode.tolist() == [0, 0, 0, 1, 1]
    assert batch.step_success.tolist() == [True, True, True, False, False]


@pytest.mark.parametrize("key, value, message", [
    ("x_t", torch.zeros(4, 2, 2), "'x_t' must have 5 rows \\(the steps table\\)"),
    ("mask", torch.ones(3, 2), "'mask' must be torch.bool"),
    ("episode_task", torch.zeros(3, dtype=torch.int64), "'episode_task' must have 2 rows"),
])
def test_a_wrong_key_is_refused(key, value, message):
    with pytest.raises(ValueError, match=message):
        Batch(**(tiny_batch() | {key: value}))
    with pytest.raises(ValueError, match="obs lacks \\['task'\\]"):
        Batch(**(tiny_batch() | {"obs": {"state": torch.zeros(3, 3)}}))
