"""``env.name: gym``: any Gymnasium env behind the chunk env contract, its demonstrations from a
user's expert, a LeRobot dataset folder or HDF5 files, and one-line errors for bad input. The
env is ``gym_toy`` (a Dict observation with an image, actions in [-2, 2], ``is_success``) and
Gymnasium's own MuJoCo Reacher (a Box observation, success from a user's function)."""

import json

import gymnasium as gym
import numpy as np
import pytest

from chunk_contract import check_chunk_contract
from stepnft.cli import main
from stepnft.config import EnvConfig, TrainConfig, load_config
from stepnft.data.demos import generate_demos, load_demos, load_or_generate_demos
from stepnft.config import DemoConfig
from stepnft.envs import make_vec_env, simulator_for
from stepnft.envs.gym import GymSpec, task_name
from stepnft.settings import SettingError

TOY = dict(name="gym", id=["gym_toy:Toy-v0"], state_keys=["agent", "target"], expert="gym_toy:expert",
           max_episode_steps=60, envs_per_task=2)


def toy_env(**kw) -> EnvConfig:
    return EnvConfig(**(TOY | kw))


def test_tasks_follow_the_env_ids_and_gym_settings_belong_to_gym():
    assert toy_env().tasks == ["Toy-v0"] and task_name("gym_pusht:gym_pusht/PushT-v0") == "PushT-v0"
    assert EnvConfig(name="gym", id=["FetchPush-v4", "FetchPickAndPlace-v4"]).tasks == ["FetchPush-v4",
                                                                                      "FetchPickAndPlace-v4"]
    spec = GymSpec.from_config(EnvConfig(name="gym", id=["gym_pusht:gym_pusht/PushT-v0", "FetchPush-v4"]))
    assert spec.env_id("PushT-v0") == "gym_pusht:gym_pusht/PushT-v0" and spec.env_id("FetchPush-v4") == "FetchPush-v4"
    with pytest.raises(SettingError, match="needs the Gymnasium env: give env.id"):
        EnvConfig(name="gym")
    with pytest.raises(SettingError, match="env.state_keys is a setting of env.name gym"):
        EnvConfig(state_keys=["agent"])
    with pytest.raises(SettingError, match="distinct names"):
        EnvConfig(name="gym", id=["a:Toy-v0", "b:Toy-v0"])
    with pytest.raises(SettingError, match="env.tasks of env.name gym are named by env.id"):
        toy_env(tasks=["other"])
    with pytest.raises(SettingError, match="env.instructions names nope"):
        toy_env(instructions={"nope": "go"})


def test_the_env_keeps_the_chunk_contract_with_state_and_image_from_declared_keys():
    sim = simulator_for(toy_env(cameras=["pixels", "render"], image_size=16))
    assert (sim.state_dim, sim.action_dim, sim.task_names(), sim.instruction("Toy-v0")) == (4, 2, ["Toy-v0"], "Toy-v0")
    env = sim.make_env("Toy-v0", n_exec=4, cameras=["pixels", "render"], image_size=16)
    first, _ = check_chunk_contract(env, 2)
    assert first["image"].shape == (2, 3, 16, 16) and first["image"].dtype == np.uint8
    raw, _ = gym.make("gym_toy:Toy-v0").reset(seed=0)  # the state is the declared entries, in order
    np.testing.assert_array_equal(first["state"], np.concatenate([raw["agent"], raw["target"]]))


def test_actions_are_mapped_onto_the_envs_bounds_and_success_ends_the_episode():
    sim = simulator_for(toy_env())
    env = sim.make_env("Toy-v0", n_exec=1, max_episode_steps=60)
    obs, _ = env.reset(seed=1)
    env.step(np.ones((1, 2), np.float32))  # +1 for the policy is the env's +2: a step of SPEED
    np.testing.assert_allclose(env.raw_obs["agent"] - obs["state"][:2], [0.1, 0.1], atol=1e-6)
    expert = sim.expert("Toy-v0", seed=0)
    expert.attach(env)
    obs, _ = env.reset(seed=1)
    for _ in range(60):
        obs, _, terminated, truncated, info = env.step(expert.act(obs)[None].astype(np.float32))
        if terminated or truncated:
            break
    assert terminated and info["success"] and info["episode_steps"] < 60
    # raw_env is the user's env itself: the same seed and the mapped action give the same state
    raw, _ = env.raw_env.reset(seed=1)
    raw, *_ = env.raw_env.step(env.actions.to_env(np.ones(2, np.float32)))
    env.reset(seed=1)
    env.step(np.ones((1, 2), np.float32))
    np.testing.assert_allclose(raw["agent"], env.raw_obs["agent"])


def test_seeded_resets_and_restored_streams_repeat_the_episodes():
    def starts(venv, seeds=None):
        return venv.reset(seed=seeds)[0]["state"]

    cfg = toy_env()
    a, b = make_vec_env(cfg, 4, seed=0), make_vec_env(cfg, 4, seed=0, )
    np.testing.assert_array_equal(starts(a, [5, 6]), starts(b, [5, 6]))
    state = a.rng_state()
    first = starts(a)
    a.set_rng_state(state)
    np.testing.assert_array_equal(starts(a), first)  # exact resume: unseeded resets continue the saved streams
    workers = make_vec_env(toy_env(num_workers=2), 4, seed=0)
    try:
        np.testing.assert_array_equal(starts(workers, [5, 6]), starts(b, [5, 6]))
    finally:
        for venv in (a, b, workers):
            venv.close()


def test_demonstrations_from_the_users_expert(tmp_path):
    cfg = toy_env()
    episodes = load_or_generate_demos(DemoConfig(path=str(tmp_path / "demos"), episodes=3), cfg, simulator_for(cfg),
                                      log=lambda _: None)
    assert len(episodes) == 3 and all(e.success and e.task == "Toy-v0" for e in episodes)
    assert np.abs(episodes[0].actions).max() <= 1.0 and episodes[0].observations.shape[1] == 4


def _recorded(cfg, n=3):
    """Expert episodes in the env's own units (what a user's dataset holds): states, actions, frames."""
    env = gym.make("gym_toy:Toy-v0")
    act = __import__("gym_toy").expert("Toy-v0", 0)
    out = []
    for seed in range(n):
        obs, _ = env.reset(seed=seed)
        rows = []
        for t in range(60):
            action = act(obs)
            rows.append((np.concatenate([obs["agent"], obs["target"]]), action, obs["pixels"]))
            obs, _, done, _, _ = env.step(action)
            if done:
                break
        out.append(rows)
    return out


def test_demonstrations_from_a_lerobot_dataset_folder(tmp_path):
    import io

    import pyarrow as pa
    import pyarrow.parquet as pq
    from PIL import Image

    root = tmp_path / "lerobot"
    (root / "meta").mkdir(parents=True)
    (root / "data" / "chunk-000").mkdir(parents=True)
    episodes = _recorded(toy_env())
    columns = {k: [] for k in ("observation.state", "action", "observation.images.pixels", "episode_index",
                               "frame_index", "task_index")}
    for e, rows in enumerate(episodes):
        for t, (state, action, frame) in enumerate(rows):
            png = io.BytesIO()
            Image.fromarray(frame).save(png, format="PNG")
            for key, value in zip(columns, (state.tolist(), action.tolist(), {"bytes": png.getvalue(), "path": None},
                                            e, t, 0)):
                columns[key].append(value)
    pq.write_table(pa.table(columns), root / "data" / "chunk-000" / "file-000.parquet")
    (root / "meta" / "info.json").write_text(json.dumps({"codebase_version": "v3.0", "features": {
        "observation.images.pixels": {"dtype": "image"}}}))
    (root / "meta" / "tasks.jsonl").write_text(json.dumps({"task_index": 0, "task": "Reach the green dot."}) + "\n")
    cfg = toy_env(cameras=["pixels"], image_size=16, instructions={"Toy-v0": "reach the green dot"})
    demos = load_demos(root, simulator_for(cfg), cameras=["pixels"], image_size=16)
    assert [len(d.actions) for d in demos] == [len(r) for r in episodes]
    assert demos[0].instruction == "reach the green dot" and demos[0].success
    np.testing.assert_allclose(demos[0].actions[0], np.clip(episodes[0][0][1] / 2, -1, 1), atol=1e-6)  # to [-1, 1]
    np.testing.assert_array_equal(demos[0].images[0, 0], episodes[0][0][2].transpose(2, 0, 1))
    wrong = toy_env(instructions={"Toy-v0": "something else"}, id=["gym_toy:Toy-v0", "CartPole-v1"])
    with pytest.raises(ValueError):
        simulator_for(wrong)  # CartPole has no success signal (nor a Box action space)


def test_demonstrations_from_hdf5_files(tmp_path):
    import h5py

    episodes = _recorded(toy_env())
    with h5py.File(tmp_path / "Toy-v0_demo.hdf5", "w") as f:
        for k, rows in enumerate(episodes):
            group = f.create_group(f"data/demo_{k}")
            group.create_dataset("obs/agent", data=np.stack([r[0][:2] for r in rows]))
            group.create_dataset("obs/target", data=np.stack([r[0][2:] for r in rows]))
            group.create_dataset("actions", data=np.stack([r[1] for r in rows]))
    demos = load_demos(tmp_path, simulator_for(toy_env()))
    assert len(demos) == 3 and demos[1].observations.shape == (len(episodes[1]) + 1, 4)
    np.testing.assert_allclose(demos[1].observations[0], episodes[1][0][0], atol=1e-6)


@pytest.mark.parametrize("overrides, expected", [
    (dict(id=["no_such_module:Toy-v0"]), "cannot import"),
    (dict(id=["NoSuchEnv-v0"]), "not found|doesn't exist|NoSuchEnv"),
    (dict(state_keys=["agent", "velocity"]), "env.state_keys entry 'velocity' is not in the observation; its keys: "
                                              "agent, target, pixels"),
    (dict(cameras=["agent"]), "not a uint8"),
    (dict(success="missing_key"), "no success signal"),
    (dict(success="gym_toy:no_such_function"), "has no no_such_function"),
])
def test_bad_input_is_one_line_before_any_work(capsys, tmp_path, overrides, expected):
    import re

    argv = ["train", "--run-dir", str(tmp_path / "run"), "--demos.path", str(tmp_path / "demos")]
    for key, value in (TOY | overrides).items():
        flag = "--env." + key.replace("_", "-")
        argv += [flag, *(value if isinstance(value, list) else [str(value)])]
    policy_cameras = overrides.get("cameras")
    if policy_cameras:
        argv += ["--policy.cameras", *policy_cameras]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and re.search(expected, err), err
    assert not (tmp_path / "run").exists() and not (tmp_path / "demos").exists()


@pytest.mark.slow
def test_train_on_a_gymnasium_env_end_to_end(tmp_path):
    run = tmp_path / "run"
    argv = ["train", "--run-dir", str(run), "--demos.path", str(tmp_path / "demos"), "--demos.episodes", "4",
            "--env.name", "gym", "--env.id", "gym_toy:Toy-v0", "--env.state-keys", "agent", "target",
            "--env.expert", "gym_toy:expert", "--env.max-episode-steps", "40", "--env.envs-per-task", "2",
            "--policy.state-dim", "4", "--policy.action-dim", "2", "--policy.hidden-dim", "64",
            "--iterations", "2", "--episodes-per-iteration", "4", "--sft.steps", "30", "--algo.minibatch-size", "32",
            "--eval.episodes", "4", "--eval.every", "1", "--eval.during-episodes", "2"]
    assert main(argv) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert set(summary["final_success"]) >= {"Toy-v0"} if isinstance(summary.get("final_success"), dict) else True
    cfg = load_config(run / "config.yaml", TrainConfig)
    assert cfg.env.name == "gym" and cfg.env.id == ["gym_toy:Toy-v0"] and cfg.env.tasks == ["Toy-v0"]
