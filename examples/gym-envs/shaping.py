"""A user's own reward shaping for FetchPush, as a Gymnasium wrapper under an id of its own.

FetchPush's dense reward is minus the cube's distance to the goal: it moves only once the cube
does, so every step before the gripper reaches the cube is progress 0 to ``labels: progress``.
``FetchPushReach-v0`` adds minus the gripper's distance to a point just behind the cube (on
the side away from the goal, where a push starts), weighted by ``reach_weight``, so getting
there is progress too. Observations, actions and success (``info["is_success"]``) are
FetchPush's own. The id imports this module: ``env.id: ["shaping:FetchPushReach-v0"]`` with
``PYTHONPATH=examples/gym-envs``; nothing in stepnft names it.
"""
import gymnasium as gym
import numpy as np

BEHIND = 0.05  # metres behind the cube's centre, away from the goal: where the expert starts its push


class ReachThenPush(gym.Wrapper):
    def __init__(self, env: gym.Env, reach_weight: float = 0.5):
        super().__init__(env)
        self.reach_weight = reach_weight

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        grip, cube, goal = obs["observation"][0:3], obs["observation"][3:6], obs["desired_goal"]
        away = cube[:2] - goal[:2]
        start = cube.copy()
        start[:2] += BEHIND * away / max(float(np.linalg.norm(away)), 1e-6)
        return obs, float(reward) - self.reach_weight * float(np.linalg.norm(grip - start)), terminated, truncated, info


def make_fetch_push_reach(reach_weight: float = 0.5, **kwargs) -> gym.Env:
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    return ReachThenPush(gym.make("FetchPush-v4", **kwargs), reach_weight)


gym.register("FetchPushReach-v0", entry_point=make_fetch_push_reach)
