"""The toy bandit behind the simulator interface (used by the fast end-to-end tests)."""

import numpy as np
import pytest

from stepnft.envs import get_simulator
from stepnft.envs.bandit import HORIZON, RADIUS, target
from stepnft.envs.base import checked_chunk


def test_an_episode_succeeds_only_if_every_action_is_on_target():
    sim = get_simulator("bandit")
    env = sim.make_env("bandit", n_exec=HORIZON)
    obs, _ = env.reset(seed=3)
    goal = target(obs["state"].astype(np.float64))
    _, reward, terminated, truncated, info = env.step(np.stack([goal, goal]).astype(np.float32))
    assert terminated and not truncated and info["success"] and reward == 1.0 and info["steps"] == HORIZON
    # A finished episode answers with a no-op.
    assert env.step(np.zeros((HORIZON, 2), np.float32))[4]["steps"] == 0

    env.reset(seed=3)
    off = goal + np.array([RADIUS * 1.5, 0.0])
    _, reward, terminated, truncated, info = env.step(np.stack([goal, off]).astype(np.float32))
    assert truncated and not terminated and not info["success"] and reward == 0.0


def test_seeded_contexts_and_a_biased_expert():
    sim = get_simulator("bandit")
    a, b = sim.make_env("bandit", seed=0), sim.make_env("bandit", seed=1)
    np.testing.assert_array_equal(a.reset(seed=7)[0]["state"], b.reset(seed=7)[0]["state"])
    assert not np.array_equal(a.reset(seed=7)[0]["state"], a.reset(seed=8)[0]["state"])
    expert = sim.expert("bandit", seed=0)
    obs = {"state": np.zeros(2, np.float32)}
    actions = np.stack([expert.act(obs) for _ in range(400)])
    assert 0.05 < np.linalg.norm(actions.mean(0) - target(obs["state"])) < 0.15  # biased, not useless


def test_step_checks_the_chunk_as_every_chunk_env_does():
    env = get_simulator("bandit").make_env("bandit", n_exec=HORIZON)
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(np.zeros((HORIZON, 2), np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2, 2\), got \(3, 2\)"):
        env.step(np.zeros((3, 2), np.float32))
    chunk = checked_chunk([[0.5, 0], [0, 0.25]], env.action_space, was_reset=True)
    assert chunk.dtype == np.float64 and chunk.shape == (2, 2)
