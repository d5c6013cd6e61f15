"""How close do a policy's failed reach-v3 episodes come? For each ODE episode from evaluation
initial states 0..N-1 (the evaluation's sampler noise), the closest hand-to-goal distance;
success needs about 5 cm. Near misses mean the policy lacks precision, not direction.

    .venv/bin/python benchmarks/reach_near_misses.py RUN/policy [--episodes 40]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from stepnft.envs.metaworld import MetaWorldChunkEnv, instruction_for
from stepnft.evaluate import episode_generators
from stepnft.policies.base import load_policy

HAND, GOAL = slice(0, 3), slice(36, 39)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("policy")
    p.add_argument("--episodes", type=int, default=40)
    p.add_argument("--tasks", nargs="+", default=["reach-v3", "push-v3", "pick-place-v3", "door-open-v3",
                                                  "drawer-open-v3"], help="the policy's task order")
    args = p.parse_args(argv)
    policy = load_policy(args.policy).eval()
    policy.processor.bind_instructions([instruction_for(t) for t in args.tasks])
    task = args.tasks.index("reach-v3")
    env = MetaWorldChunkEnv("reach-v3", n_exec=policy.config.n_exec, max_episode_steps=200)
    closest, success = [], []
    for e in range(args.episodes):
        obs, _ = env.reset(seed=e)
        generator, done, best = episode_generators([e])[0], False, np.inf
        while not done:
            raw = {"state": torch.as_tensor(obs["state"][None]), "task": torch.tensor([task])}
            chunk = policy.sample(policy.processor(raw), generator=generator).actions[0, : policy.config.n_exec]
            obs, _, terminated, truncated, info = env.step(chunk.clamp(-1, 1).numpy())
            best = min(best, float(np.linalg.norm(obs["state"][HAND] - obs["state"][GOAL])))
            done = terminated or truncated
        closest.append(best)
        success.append(bool(info["success"]))
    env.close()
    closest, success = np.array(closest), np.array(success)
    misses = np.sort(closest[~success])
    print(f"reach-v3: success {success.mean():.2f} over {args.episodes} episodes; closest approach of the "
          f"{len(misses)} failures (m): {np.round(misses, 3).tolist()}")
    return {"success": float(success.mean()), "failure_closest_m": misses.tolist()}


if __name__ == "__main__":
    main()
