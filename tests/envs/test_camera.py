"""Camera observations: upright images, rendered once per policy call, proprioceptive state,
the goal marker, and parallel rendering in worker processes (bit-identical to one process)."""

import numpy as np
import pytest

from stepnft.envs.base import RenderingError
from stepnft.envs.metaworld import MetaWorldChunkEnv, make_metaworld_vec_env
from stepnft.envs.metaworld.camera import CameraRenderer
from stepnft.envs.metaworld.env import GOAL_MARKER_RADIUS

pytestmark = pytest.mark.filterwarnings("ignore:Constant:UserWarning")


def camera_env(task="reach-v3", cameras=("corner",), size=16, **kwargs) -> MetaWorldChunkEnv:
    try:
        return MetaWorldChunkEnv(task, cameras=list(cameras), image_size=size, **kwargs)
    except RenderingError as err:
        pytest.skip(f"no offscreen rendering here (EGL): {err}")


def marker_row(env: MetaWorldChunkEnv, z: float) -> float:
    """The image row of the goal marker placed at height ``z``: the centroid of the pixels that
    change when the marker is hidden."""
    sim = env._sim
    goal = sim.model.site("goal").id
    sim.data.site_xpos[goal] = [0.0, 0.75, z]
    shown = env._cameras.frame(sim.data).astype(int)
    alpha = sim.model.site_rgba[goal, 3]
    sim.model.site_rgba[goal, 3] = 0.0
    hidden = env._cameras.frame(sim.data).astype(int)
    sim.model.site_rgba[goal, 3] = alpha
    rows = np.nonzero(np.abs(shown - hidden).sum(-1))[0]
    assert len(rows), "the marker should be in view"
    return rows.mean()


@pytest.mark.parametrize("camera", ["corner", "corner2", "corner3", "corner4"])
def test_images_are_upright(camera):
    # MetaWorld mounts corner..corner4 upside down: a marker raised in the world must rise in the image.
    env = camera_env(cameras=[camera], size=64)
    env.reset(seed=0)
    assert marker_row(env, 0.35) < marker_row(env, 0.05) - 2
    env.close()


def test_images_are_rendered_once_per_policy_call(monkeypatch):
    calls = []
    views = CameraRenderer.views
    monkeypatch.setattr(CameraRenderer, "views", lambda self, data: calls.append(1) or views(self, data))
    env = camera_env(cameras=["corner", "topview"], n_exec=4, max_episode_steps=10)
    obs, _ = env.reset(seed=0)
    assert obs["image"].dtype == np.uint8 and obs["image"].shape == (2, 3, 16, 16)
    assert env.observation_space["image"].contains(obs["image"]) and len(calls) == 1
    first = obs["image"]
    obs, *_ = env.step(np.ones((4, 4), dtype=np.float32))
    assert len(calls) == 2 and not np.array_equal(obs["image"], first)  # 4 env steps, one render
    truncated = False
    while not truncated:
        last, _, _, truncated, _ = env.step(np.zeros((4, 4), dtype=np.float32))
    assert len(calls) == 4  # 10 steps: chunks of 4, 4 and 2
    ended = env.step(np.zeros((4, 4), dtype=np.float32))[0]  # a no-op on an ended episode: no render
    assert len(calls) == 4 and np.array_equal(ended["image"], last["image"])
    env.close()


def test_proprioceptive_state_and_goal_marker():
    full = MetaWorldChunkEnv("push-v3")
    env = camera_env("push-v3", state_obs="proprio")
    full_obs, _ = full.reset(seed=3)
    obs, _ = env.reset(seed=3)
    assert obs["state"].shape == (4,) and env.observation_space["state"].shape == (4,)
    np.testing.assert_array_equal(obs["state"], full_obs["state"][:4])  # hand xyz + gripper, nothing else
    goal = env._sim.model.site("goal").id
    assert env._sim.model.site_size[goal, 0] == GOAL_MARKER_RADIUS > full._sim.model.site_size[goal, 0]
    with pytest.raises(ValueError, match="state_obs"):
        MetaWorldChunkEnv("push-v3", state_obs="joints")
    with pytest.raises(ValueError, match="unknown camera 'front'; this scene's cameras: topview, corner"):
        MetaWorldChunkEnv("push-v3", cameras=["front"])
    env.close()
    full.close()


def test_workers_render_in_parallel_bit_identically():
    try:
        sync = make_metaworld_vec_env(["reach-v3", "push-v3"], 2, 4, 12, seed=1, cameras=["corner"], image_size=16)
    except RenderingError as err:
        pytest.skip(f"no offscreen rendering here (EGL): {err}")
    sync.reset()  # this process has rendered: the workers must still start (forkserver)
    sharded = make_metaworld_vec_env(["reach-v3", "push-v3"], 2, 4, 12, seed=1, num_workers=2, cameras=["corner"],
                                     image_size=16)
    rng = np.random.default_rng(0)
    for venv in (sync, sharded):
        venv.reset(seed=[5, 6, 7, 8])
    for _ in range(3):
        actions = rng.uniform(-1, 1, (4, 4, 4)).astype(np.float32)
        a, b = sync.step(actions)[0], sharded.step(actions)[0]
        np.testing.assert_array_equal(a["image"], b["image"])
        np.testing.assert_array_equal(a["state"], b["state"])
    assert a["image"].shape == (4, 1, 3, 16, 16) and a["image"].std() > 0
    sync.close()
    sharded.close()
