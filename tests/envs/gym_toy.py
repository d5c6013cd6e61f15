"""A Gymnasium env for the tests of ``env.name: gym`` (registered as ``Toy-v0`` on import, so the
id ``gym_toy:Toy-v0`` makes it): a point moves towards a random target in the plane. Its Dict
observation has two vectors and an image, its actions are in [-2, 2] (not the policy's [-1, 1]),
its info reports ``is_success``, and it terminates on success as many robot envs do."""

import gymnasium as gym
import numpy as np

SPEED = 0.1
RADIUS = 0.1


class Toy(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, render_mode=None, reward_type="dense"):
        self.render_mode, self.reward_type = render_mode, reward_type
        self.observation_space = gym.spaces.Dict({
            "agent": gym.spaces.Box(-2, 2, (2,), np.float32), "target": gym.spaces.Box(-1, 1, (2,), np.float32),
            "pixels": gym.spaces.Box(0, 255, (16, 16, 3), np.uint8)})
        self.action_space = gym.spaces.Box(-2.0, 2.0, (2,), np.float32)

    def _obs(self):
        pixels = np.zeros((16, 16, 3), np.uint8)
        for value, channel in ((self.agent, 0), (self.target, 1)):
            x, y = np.clip(((value + 2) * 4).astype(int), 0, 15)
            pixels[y, x, channel] = 255
        return {"agent": self.agent.astype(np.float32), "target": self.target.astype(np.float32), "pixels": pixels}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.agent = self.np_random.uniform(-1, 1, 2)
        self.target = self.np_random.uniform(-1, 1, 2)
        return self._obs(), {}

    def step(self, action):
        self.agent = np.clip(self.agent + SPEED * np.clip(action, -2, 2) / 2, -2, 2)
        distance = float(np.linalg.norm(self.agent - self.target))
        success = distance < RADIUS
        reward = -distance if self.reward_type == "dense" else float(success)
        return self._obs(), reward, success, False, {"is_success": success}

    def render(self):
        return np.repeat(np.repeat(self._obs()["pixels"], 2, 0), 2, 1)  # 32 x 32


def expert(task, seed):
    """The scripted expert ``env.expert`` names: straight to the target, in the env's units (a
    little noise from its own seeded stream, so demonstrations differ)."""
    rng = np.random.default_rng(seed)

    def act(obs):
        direction = (obs["target"] - obs["agent"]) / SPEED * 2
        return np.clip(direction + rng.normal(0, 0.2, 2), -2, 2)

    return act


def near_target(obs, info):
    """A success function ``env.success`` may name (module:function)."""
    return bool(np.linalg.norm(obs["agent"] - obs["target"]) < 2 * RADIUS)


def not_callable_here(obs, info):
    raise RuntimeError("broken success function")


gym.register("Toy-v0", entry_point=Toy, max_episode_steps=100)
