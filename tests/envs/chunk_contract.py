"""The chunk env contract (stepnft.envs.base) checked on any simulator's chunk env of 4 actions a call."""

import numpy as np
import pytest


def check_chunk_contract(env, action_dim: int) -> tuple[dict, float]:
    """Reset and step counts, truncation at the cap (set to 6 here, then restored), a no-op step
    on an ended episode, the idle reset, and the chunk's shape check. Returns the first reset's
    observation and the first step's reward, for a simulator's own checks."""
    cap = env.max_episode_steps
    env.max_episode_steps = 6
    try:
        first, info = env.reset(seed=0)
        assert info == {"success": False, "steps": 0, "episode_steps": 0}
        chunk = np.zeros((4, action_dim), np.float32)
        obs, first_reward, terminated, truncated, info = env.step(chunk)
        assert (info["steps"], info["episode_steps"], terminated, truncated) == (4, 4, False, False)
        obs, reward, terminated, truncated, info = env.step(chunk)
        assert (info["steps"], info["episode_steps"], truncated, info["success"]) == (2, 6, True, False)
        after, reward, terminated, truncated, info = env.step(np.ones((4, action_dim), np.float32))
        assert (reward, info["steps"], truncated) == (0.0, 0, True)  # stepping an ended episode: a no-op
        np.testing.assert_array_equal(after["state"], obs["state"])
        idle, info = env.reset(options={"idle": True})
        assert info["episode_steps"] == 0 and env.step(chunk)[3] and env.step(chunk)[4]["steps"] == 0
        with pytest.raises(ValueError, match="shape"):
            env.reset(seed=0)
            env.step(np.zeros((3, action_dim), np.float32))
    finally:
        env.max_episode_steps = cap
    return first, first_reward
