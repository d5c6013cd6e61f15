"""ManiSkill3 behind the simulator interface (the optional extra stepnft[maniskill], and a
Vulkan device: both skip the module with their reason when absent)."""

import json

import numpy as np
import pytest

try:
    from stepnft.envs.maniskill import EXPERTS, TASKS, ManiSkill
except ImportError as err:
    pytest.skip(f"the ManiSkill extra is not installed: {err}", allow_module_level=True)

from chunk_contract import check_chunk_contract
from stepnft.cli import main
from stepnft.data.demos import load_demos
from stepnft.envs import get_simulator, make_vec_env
from stepnft.envs.maniskill.env import maniskill_seed
from stepnft.envs.maniskill.tasks import STATE_DIM, STATE_LAYOUTS

TASK = "PushCube-v1"

# ManiSkill 3.0.1 calls numpy on torch tensors and Logger.warn: its own warnings, not stepnft's.
pytestmark = [pytest.mark.filterwarnings("ignore:__array_wrap__:DeprecationWarning"),
              pytest.mark.filterwarnings("ignore:The 'warn' method:DeprecationWarning")]


@pytest.fixture(scope="module")
def sim():
    return get_simulator("maniskill")


@pytest.fixture(scope="module")
def env(sim):
    try:
        env = sim.make_env(TASK, n_exec=4, max_episode_steps=50, seed=0)
    except ValueError as err:
        if "Vulkan" not in str(err):
            raise
        pytest.skip(f"no usable Vulkan device here: {err}")
    yield env
    env.close()


def test_tasks_instructions_and_checks(sim):
    assert sim.task_names() == list(TASKS) and len(TASKS) >= 10
    assert set(EXPERTS) >= {"PickCube-v1", "PushCube-v1", "PullCube-v1", "StackCube-v1"}
    assert all(sim.instruction(t) == sim.instruction(t).strip() != "" for t in TASKS)
    assert sim.validate_tasks("PickCube-v1,PushCube-v1") == ["PickCube-v1", "PushCube-v1"]
    with pytest.raises(ValueError, match="unknown ManiSkill task 'PickSingleYCB-v1'"):
        sim.validate_tasks(["PickSingleYCB-v1"])
    with pytest.raises(ValueError, match="scripted experts for"):
        sim.expert("PlugCharger-v1", 0)
    with pytest.raises(ValueError, match="state_obs"):
        sim.state_dim_for("proprio")
    with pytest.raises(ValueError, match="no perturbation"):
        sim.make_env(TASK, perturbations=["table_color"])
    # Demonstration seeds (2**32 + k) land apart from training and evaluation seeds (< 2**31).
    assert maniskill_seed(5) == 5 and maniskill_seed(2**32 + 7) == 2**31 + 7


def test_state_layouts_match_the_simulator(sim, env):
    for task in STATE_LAYOUTS:
        task_env = env if task == TASK else sim.make_env(task, seed=0)
        try:
            obs, _ = task_env.reset(seed=1)
            base, layout, state = task_env._base, STATE_LAYOUTS[task], obs["state"]
            assert state.shape == (STATE_DIM,) and state.dtype == np.float32
            np.testing.assert_allclose(state[layout["tcp_pose"]], base.agent.tcp.pose.raw_pose[0].numpy(), atol=1e-6)
            cube = base.cubeA if task == "StackCube-v1" else base.cube if task == "PickCube-v1" else base.obj
            name = "cubeA_pose" if task == "StackCube-v1" else "obj_pose"
            np.testing.assert_allclose(state[layout[name]], cube.pose.raw_pose[0].numpy(), atol=1e-6)
            np.testing.assert_allclose(state[layout["qpos"]], base.agent.robot.get_qpos()[0].numpy(), atol=1e-6)
            end = max(part.stop for part in layout.values())
            assert np.all(state[end:] == 0)  # the padding
        finally:
            if task_env is not env:
                task_env.close()


def test_reset_is_a_function_of_the_seed(sim, env):
    first, _ = env.reset(seed=3)
    rng = np.random.default_rng(0)
    chunks = rng.uniform(-1, 1, (3, 4, 7)).astype(np.float32)
    played = [env.step(chunk)[0]["state"] for chunk in chunks]
    other, _ = env.reset(seed=4)
    again, _ = env.reset(seed=3)
    replayed = [env.step(chunk)[0]["state"] for chunk in chunks]
    fresh = sim.make_env(TASK, n_exec=4, seed=12345)
    try:
        in_fresh, _ = fresh.reset(seed=3)
    finally:
        fresh.close()
    np.testing.assert_array_equal(again["state"], first["state"])
    np.testing.assert_array_equal(in_fresh["state"], first["state"])
    assert not np.array_equal(other["state"], first["state"])
    np.testing.assert_allclose(np.stack(replayed), np.stack(played), atol=1e-5)  # the same actions, the same episode
    # Unseeded resets continue the env's own stream (seeded at construction or by the last seeded reset).
    env.reset(seed=9)
    follow = env.reset()[0]["state"]
    env.reset(seed=9)
    np.testing.assert_array_equal(env.reset()[0]["state"], follow)


def test_chunk_contract(env):
    obs, reward = check_chunk_contract(env, 7)
    assert "image" not in obs
    assert 0 <= reward <= 4  # normalized_dense: at most 1 per step
    assert env.max_episode_steps == 50


def test_success_ends_the_episode(sim, env):
    expert = sim.expert(TASK, 0)
    obs, _ = env.reset(seed=0)
    for _ in range(12):
        chunk = np.stack([np.clip(expert.act(obs), -1, 1)] * 4).astype(np.float32)
        obs, _, terminated, truncated, info = env.step(chunk)
        if terminated or truncated:
            break
    assert terminated and not truncated and info["success"] and info["steps"] <= 4


def test_cameras_and_video(sim, env):
    cam = sim.make_env("StackCube-v1", n_exec=2, seed=0, cameras=["base_camera", "hand_camera"], image_size=32,
                       render_size=(48, 40))
    try:
        obs, _ = cam.reset(seed=0)
        assert obs["image"].shape == (2, 3, 32, 32) and obs["image"].dtype == np.uint8
        assert obs["image"].std() > 5  # a scene, not a blank
        moved, *_ = cam.step(np.tile([0, 0, 1, 0, 0, 0, 1], (2, 1)).astype(np.float32))
        assert not np.array_equal(moved["image"][1], obs["image"][1])  # the wrist camera moved up
        frame = cam.render()
        assert frame.shape == (48, 40, 3) and frame.dtype == np.uint8
    finally:
        cam.close()
    with pytest.raises(ValueError, match="unknown ManiSkill camera 'hand_camera' for PushCube-v1"):
        sim.make_env(TASK, cameras=["hand_camera"])


@pytest.mark.parametrize("task", ["PickCube-v1", "PushCube-v1", "PullCube-v1", "StackCube-v1"])
def test_expert_succeeds_on_most_seeds(sim, env, task):  # env: skips without Vulkan
    env = sim.make_env(task, n_exec=1, max_episode_steps=TASKS[task].max_episode_steps, seed=0)
    expert = sim.expert(task, 0)
    wins = 0
    try:
        for seed in range(5):
            obs, _ = env.reset(seed=seed)
            done = False
            while not done:
                obs, _, terminated, truncated, info = env.step(np.clip(expert.act(obs), -1, 1)[None].astype(np.float32))
                done = terminated or truncated
            wins += info["success"]
    finally:
        env.close()
    assert wins >= 4, f"{task}: the expert succeeded on {wins} of 5 seeds"


def test_vector_env_mixes_tasks(env):
    from stepnft.config import EnvConfig

    cfg = EnvConfig(name="maniskill", tasks=["PickCube-v1", "PushCube-v1"], envs_per_task=1, max_episode_steps=8)
    venv = make_vec_env(cfg, n_exec=4, seed=0)
    try:
        obs, _ = venv.reset(seed=[0, 1])
        assert obs["state"].shape == (2, STATE_DIM)
        _, _, _, _, info = venv.step(np.zeros((2, 4, 7), np.float32))
        assert list(info["steps"]) == [4, 4]
    finally:
        venv.close()


@pytest.mark.slow
def test_demos_then_train_end_to_end(env, tmp_path, capsys):
    demos = tmp_path / "demos"
    assert main(["demos", "--env.name", "maniskill", "--env.tasks", "PushCube-v1,PullCube-v1",
                 "--demos.path", str(demos), "--demos.episodes", "2", "--env.max-episode-steps", "50"]) == 0
    episodes = load_demos(demos)
    assert len(episodes) == 4 and all(e.success for e in episodes)
    assert json.loads((demos / "manifest.json").read_text())["generator"]["simulator"] == "maniskill"
    run = tmp_path / "run"
    assert main(["train", "--run-dir", str(run), "--demos.path", str(demos), "--demos.episodes", "2",
                 "--env.name", "maniskill", "--env.tasks", "PushCube-v1,PullCube-v1", "--env.envs-per-task", "1",
                 "--env.max-episode-steps", "16", "--policy.state-dim", str(STATE_DIM), "--policy.action-dim", "7",
                 "--iterations", "2", "--episodes-per-iteration", "2", "--policy.hidden-dim", "32",
                 "--sft.steps", "10", "--sft.batch-size", "32", "--algo.minibatch-size", "16",
                 "--eval.episodes", "1", "--eval.every", "2", "--eval.during-episodes", "1", "--num-threads", "1"]) == 0
    assert (run / "policy").is_dir()
