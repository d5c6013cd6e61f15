"""Run each scripted expert on N seeded episodes; print success rate and length.

    python examples/gym-envs/check_experts.py --episodes 50 [--env FetchPush-v4]

An episode counts as a success if info["is_success"] is true at its last step
(Fetch never terminates, so every episode runs to the TimeLimit of 50 steps;
envs that terminate on success end earlier). The "first" column is the mean
step at which success was first reached.
"""
import argparse
import os
import sys
import time

import gymnasium as gym
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from experts import EXPERTS  # noqa: E402


def make_env(env_id):
    if env_id.startswith("Fetch"):
        import gymnasium_robotics
        gym.register_envs(gymnasium_robotics)
        return gym.make(env_id)
    if env_id.startswith("gym_pusht"):
        import gym_pusht  # noqa: F401  (registers gym_pusht/PushT-v0)
        return gym.make(env_id, obs_type="state")
    return gym.make(env_id)


def run(env_id, episodes, seed0=0):
    env, factory = make_env(env_id), EXPERTS[env_id]
    succ, lengths, first = [], [], []
    t0 = time.time()
    for ep in range(episodes):
        seed = seed0 + ep
        obs, _ = env.reset(seed=seed)
        policy = factory(env_id, seed)  # fresh policy state per episode
        done, steps, hit = False, 0, None
        while not done:
            obs, _, terminated, truncated, info = env.step(policy(obs))
            steps += 1
            if hit is None and info.get("is_success"):
                hit = steps
            done = terminated or truncated
        succ.append(bool(info.get("is_success")))
        lengths.append(steps)
        if hit is not None:
            first.append(hit)
    dt = time.time() - t0
    print(f"{env_id:24s} success {np.mean(succ):.2f} ({sum(succ)}/{episodes})  "
          f"mean_len {np.mean(lengths):.1f}  first_success {np.mean(first) if first else float('nan'):.1f}  "
          f"steps/s {sum(lengths) / dt:.0f}")
    env.close()
    return np.mean(succ)


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--env", action="append", help="env id (repeatable); default: all experts")
    a = p.parse_args()
    for env_id in a.env or EXPERTS:
        run(env_id, a.episodes)
