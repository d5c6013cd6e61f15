"""LIBERO behind the simulator interface (the optional extra stepnft[libero])."""

import json

import numpy as np
import pytest

try:
    from stepnft.envs.libero import LIBERO, SUITES
except ImportError as err:
    pytest.skip(f"the LIBERO extra is not installed: {err}", allow_module_level=True)

from chunk_contract import check_chunk_contract
from stepnft.cli import main
from stepnft.data.demos import demos_to_chunks, load_demos
from stepnft.envs import get_simulator, make_vec_env
from stepnft.envs.libero.datasets import load_dataset
from stepnft.envs.libero.scripted import POSITION_GAIN, record_demos, record_episode
from stepnft.envs.libero.suites import all_tasks, initial_states

SOUP = "pick_up_the_alphabet_soup_and_place_it_in_the_basket"
BENCHMARK_SUITES = ("libero_spatial", "libero_object", "libero_goal", "libero_10")


@pytest.fixture(scope="module")
def sim():
    return get_simulator("libero")


@pytest.fixture(scope="module")
def env(sim):
    env = sim.make_env(SOUP, n_exec=4, max_episode_steps=280, seed=0, cameras=["agentview"], image_size=32)
    yield env
    env.close()


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    """One scripted demonstration of SOUP from initial state 0, as a LIBERO HDF5 file with
    16 px agentview frames."""
    out = tmp_path_factory.mktemp("libero_demos")
    record_demos(SOUP, 1, out, max_attempts=1, cameras=("agentview",), image_size=16)
    return out


def test_suites_expand_to_their_tasks_each_with_an_instruction(sim):
    for suite in BENCHMARK_SUITES:
        tasks = sim.validate_tasks([suite])
        assert len(tasks) == 10 and len(set(tasks)) == 10
        for task in tasks:
            instruction = sim.instruction(task)
            assert instruction and instruction == instruction.strip()
            # The instruction names what the task definition's own language line names.
            assert set(instruction.split()) & set(all_tasks()[task].bddl_instruction().lower().split())
            assert initial_states(task).shape[0] == 50
    assert sim.validate_tasks(f"{SOUP},libero_goal")[0] == SOUP
    assert set(SUITES) >= set(BENCHMARK_SUITES)
    with pytest.raises(ValueError, match="libero_spatial"):
        sim.validate_tasks(["libero_nope"])
    with pytest.raises(ValueError, match="no scripted experts"):
        sim.expert(SOUP, 0)


def test_demos_command_explains_there_are_no_experts(tmp_path, capsys):
    assert main(["demos", "--env.name", "libero", "--env.tasks", SOUP, "--demos.path", str(tmp_path / "d")]) == 2
    assert "no scripted experts" in capsys.readouterr().err


def test_options_are_checked(sim):
    with pytest.raises(ValueError, match="unknown LIBERO camera 'corner'"):
        sim.make_env(SOUP, cameras=["corner"])
    with pytest.raises(ValueError, match="no perturbation"):
        sim.make_env(SOUP, perturbations=["table_color"])
    for check in (lambda: sim.state_dim_for("objects"), lambda: sim.make_env(SOUP, state_obs="objects")):
        with pytest.raises(ValueError, match="state_obs is full .* got 'objects'"):
            check()
    assert sim.state_dim_for("proprio") == 8 and sim.state_dim_for("full") == 64 and sim.state_dim_for("interest") == 22
    np.testing.assert_array_equal(sim.policy_state(np.arange(64.0), "interest"), np.arange(22.0))
    with pytest.raises(ValueError, match="--env.state-obs proprio"):  # demonstrations without simulator states
        sim.policy_state(np.zeros((3, 8)), "full")
    np.testing.assert_array_equal(sim.policy_state(np.arange(64.0), "proprio"), np.arange(8.0))


def test_reset_is_a_function_of_the_seed(sim, env):
    first, _ = env.reset(seed=3)
    assert first["state"].shape == (64,) and first["image"].shape == (1, 3, 32, 32) and first["image"].dtype == np.uint8
    rng = np.random.default_rng(0)
    for chunk in rng.uniform(-1, 1, (5, 4, 7)):
        env.step(chunk.astype(np.float32))
    again, _ = env.reset(seed=3)
    wrapped, _ = env.reset(seed=53)  # 50 initial states: seed -> state seed % 50
    other, _ = env.reset(seed=4)
    fresh = sim.make_env(SOUP, n_exec=4, seed=12345, cameras=["agentview"], image_size=32)
    try:
        in_fresh, _ = fresh.reset(seed=3)
    finally:
        fresh.close()
    for obs in (again, wrapped, in_fresh):
        np.testing.assert_array_equal(obs["state"], first["state"])
        np.testing.assert_array_equal(obs["image"], first["image"])
    assert not np.array_equal(other["image"], first["image"])


def test_the_interest_state_is_the_full_state_up_to_the_objects_of_interest(sim, env):
    """``interest``: the proprioception, then the soup can and the basket (the task's objects of
    interest), exactly the full state's first 22 values, at reset and after a chunk."""
    small = sim.make_env(SOUP, n_exec=4, max_episode_steps=280, seed=0, state_obs="interest")
    try:
        assert small.observation_space["state"].shape == (22,)
        chunk = np.tile(np.array([0.3, 0.0, -0.2, 0.0, 0.0, 0.0, -1.0], np.float32), (4, 1))
        for full, part in ((env.reset(seed=3)[0], small.reset(seed=3)[0]), (env.step(chunk)[0], small.step(chunk)[0])):
            assert part["state"].shape == (22,) and np.linalg.norm(part["state"][8:15]) > 0
            np.testing.assert_array_equal(part["state"], full["state"][:22])
    finally:
        small.close()


def test_noisy_demonstrations_keep_the_controllers_actions_for_the_states_visited(sim):
    """DART: with ``action_noise`` the hand goes elsewhere, and every recorded action is still
    the controller's for the state recorded beside it (here its first phase: 12 cm above the can)."""
    one = sim.make_env(SOUP, n_exec=1, max_episode_steps=280, seed=0, state_obs="interest")
    try:
        clean, noisy = record_episode(one, 0), record_episode(one, 0, action_noise=0.3)
        obs, _ = one.reset(seed=0)
    finally:
        one.close()
    assert clean is not None and noisy is not None  # the controller recovers from the noise
    assert not np.allclose(noisy["ee_pos"][5], clean["ee_pos"][5], atol=1e-3)
    target = obs["state"][8:11] + np.array([0.0, 0.0, 0.12])
    expected = np.clip(POSITION_GAIN * (target - noisy["ee_pos"][:10]), -1.0, 1.0)
    np.testing.assert_allclose(noisy["actions"][:10, :3], expected, atol=2e-3)
    assert np.all(noisy["actions"][:, 3:6] == 0) and set(np.unique(noisy["actions"][:, 6])) <= {-1.0, 1.0}
    with pytest.raises(ValueError, match="action_noise"):
        record_demos(SOUP, 1, "/nonexistent", action_noise=-0.1)


def test_the_shaped_reward_rises_through_a_scripted_pick_and_place_and_is_1_at_success(sim):
    """``reward="shaped"``: robosuite's staged pick-and-place reward: near 0 far from the can,
    the grasp stage (0.35) once held, over 0.5 lifted, up to 0.7 over the basket, 1 at success;
    the sparse reward is 0 until then. A task that moves nothing has none."""
    rewards = {}
    for kind in ("sparse", "shaped"):
        one = sim.make_env(SOUP, n_exec=1, max_episode_steps=280, seed=0, state_obs="interest", reward=kind)
        trace, step = [], one.step
        one.step = lambda chunk: (out := step(chunk), trace.append(out[1]))[0]
        try:
            assert record_episode(one, 0) is not None
        finally:
            one.close()
        rewards[kind] = np.array(trace)
    sparse, shaped = rewards["sparse"], rewards["shaped"]
    assert len(sparse) == len(shaped) and sparse[-1] == shaped[-1] == 1.0 and not sparse[:-1].any()
    assert shaped[0] < 0.05 and 0.35 <= shaped[len(shaped) // 2] < 0.7 and shaped[-2] > 0.6
    assert np.all(shaped[:-1] <= 0.7)
    with pytest.raises(ValueError, match="pick-and-place tasks .* use reward sparse"):
        sim.make_env("turn_on_the_stove", reward="shaped")
    with pytest.raises(ValueError, match="sparse .* or shaped, got 'dense'"):
        sim.make_env(SOUP, reward="dense")


def test_a_random_placement_is_none_of_the_benchmark_initial_states(env):
    """``reset(options={"placement": k})``: LIBERO's own random placement with seed k, the same
    every time, other for another k, and off the 50 evaluation states (where the scripted
    recorder's demonstrations start with --first-placement)."""
    first = env.reset(options={"placement": 1000})[0]["state"]
    again = env.reset(options={"placement": 1000})[0]["state"]
    other = env.reset(options={"placement": 1001})[0]["state"]
    np.testing.assert_array_equal(first, again)
    xy = np.r_[8:10, 15:17, 22:24, 29:31]  # x, y of the can, the basket and two other objects
    assert np.linalg.norm(first[xy] - other[xy]) > 1e-3
    benchmark = np.stack([env.reset(seed=k)[0]["state"][xy] for k in range(50)])
    assert np.min(np.linalg.norm(benchmark - first[xy], axis=1)) > 1e-3


def test_chunk_contract(env):
    check_chunk_contract(env, 7)
    assert env.max_episode_steps == 280


def test_a_replayed_demonstration_reaches_success_from_the_task_predicate(env, demo_dir):
    import h5py

    (file,) = demo_dir.rglob("*.hdf5")
    with h5py.File(file) as f:
        states = f["data/demo_0/states"][()]
    (demo,) = load_demos(demo_dir, get_simulator("libero"), cameras=["agentview"], image_size=16)
    assert demo.task == SOUP and demo.success and len(demo.actions) == len(states)
    assert demo.images.shape == (len(states) + 1, 1, 3, 16, 16)
    # The full state: proprioception, then the objects' poses read from the recorded MuJoCo
    # states (the soup can and the basket, the task's objects of interest, first).
    assert demo.observations.shape == (len(states) + 1, 64)
    can, basket = demo.observations[0, 8:15], demo.observations[0, 15:22]
    assert np.linalg.norm(can[:3] - basket[:3]) > 0.05 and abs(np.linalg.norm(can[3:]) - 1) < 1e-4
    last = demo.observations[-1, 8:15]
    assert np.linalg.norm(last[:3] - demo.observations[-1, 15:18]) < np.linalg.norm(can[:3] - basket[:3])  # moved in
    actions = demo.actions
    pad = -len(actions) % 4
    chunks = np.concatenate([actions, np.repeat(actions[-1:], pad, 0)]).reshape(-1, 4, 7)
    obs, _ = env.reset(seed=0)  # the initial state the demonstration was recorded from
    np.testing.assert_allclose(env.sim_state(), states[0], atol=1e-9)
    # (robosuite's step observation lags its state by one 2 ms physics substep: not bit-equal)
    np.testing.assert_allclose(obs["state"], demo.observations[0], atol=1e-3)
    successes = []
    for chunk in chunks:
        _, reward, terminated, _, info = env.step(chunk)
        successes.append(info["success"])
    assert successes[-1] and terminated and reward > 0
    assert not any(successes[:-3])  # success comes from placing the can, at the end
    # Any recorded state can be a start (exactly; the gripper's command ramp is not part of it).
    env.reset(options={"init_state": states[50]})
    np.testing.assert_allclose(env.sim_state(), states[50], atol=1e-9)
    # The same actions with the gripper never closing leave the can where it stood.
    env.reset(seed=0)
    for chunk in chunks:
        open_hand = chunk.copy()
        open_hand[:, 6] = -1.0
        _, _, _, truncated, info = env.step(open_hand)
    assert not info["success"]


@pytest.mark.slow
def test_worker_processes_step_like_one_process():
    from stepnft.config import EnvConfig

    results = []
    for workers in (0, 1):
        cfg = EnvConfig(name="libero", tasks=[SOUP], envs_per_task=1, num_workers=workers)
        venv = make_vec_env(cfg, n_exec=4, seed=0)
        try:
            obs, _ = venv.reset(seed=[7])
            chunk = np.random.default_rng(0).uniform(-1, 1, (1, 4, 7)).astype(np.float32)
            after, reward, _, _, info = venv.step(chunk)
            results.append((obs["state"], after["state"], reward, info["steps"]))
        finally:
            venv.close()
    for a, b in zip(*results):
        np.testing.assert_array_equal(a, b)


def test_the_collector_records_camera_observations():
    import torch

    from stepnft.config import EnvConfig
    from stepnft.policies.base import make_policy
    from stepnft.policies.flow import FlowPolicyConfig
    from stepnft.rollout.collector import Collector
    from stepnft.rollout.plan import EpisodePlan, RolloutSpec

    cfg = EnvConfig(name="libero", tasks=[SOUP], envs_per_task=1, max_episode_steps=8, state_obs="proprio",
                    cameras=["agentview", "robot0_eye_in_hand"], image_size=16)
    collector = Collector(make_vec_env(cfg, n_exec=4, seed=0), seed=0)
    try:
        torch.manual_seed(0)
        policy = make_policy(FlowPolicyConfig(state_dim=8, action_dim=7, lang_dim=0, horizon=4, n_exec=4))
        batch = collector.play(policy, EpisodePlan([0], [0], [0]), 0.3, record=RolloutSpec(0.3))
    finally:
        collector.close()
    assert batch.env_steps == 8 and batch.num_calls == 2
    assert batch.obs["image"].shape == (2, 2, 3, 16, 16) and batch.obs["image"].dtype == torch.uint8
    assert not torch.equal(batch.obs["image"][:, 0], batch.obs["image"][:, 1])  # scene and wrist differ


def test_hdf5_loader_reads_libero_layout(tmp_path):
    """A file written by hand in the layout of LIBERO's published datasets."""
    import h5py

    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (2, 5, 6, 6, 3), dtype=np.uint8)
    path = tmp_path / "libero_object" / f"{SOUP}_demo.hdf5"
    path.parent.mkdir()
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["problem_info"] = json.dumps({"language_instruction": "Pick up the alphabet soup and place it in "
                                                 "the basket", "problem_name": "libero_floor_manipulation"})
        data.attrs["bddl_file_name"] = f"/somewhere/bddl_files/libero_object/{SOUP}.bddl"
        for k in (1, 0):
            demo = data.create_group(f"demo_{k}")
            demo.create_dataset("actions", data=np.full((5, 7), k, np.float64))
            demo.create_dataset("states", data=np.zeros((5, 3)))  # not this model's layout: no object poses
            demo.create_dataset("dones", data=np.array([0, 0, 0, 0, 1], np.uint8))
            obs = demo.create_group("obs")
            obs.create_dataset("ee_pos", data=np.full((5, 3), 1.0 + k))
            obs.create_dataset("ee_ori", data=np.full((5, 3), 2.0))
            obs.create_dataset("gripper_states", data=np.full((5, 2), 3.0))
            obs.create_dataset("joint_states", data=np.zeros((5, 7)))
            obs.create_dataset("agentview_rgb", data=frames[k])
            obs.create_dataset("eye_in_hand_rgb", data=frames[1 - k])
    demos = load_dataset(tmp_path, ["agentview", "robot0_eye_in_hand"], image_size=6)
    assert [d.actions[0, 0] for d in demos] == [0, 1]  # demo_0 first
    first = demos[0]
    assert first.task == SOUP and first.instruction == LIBERO().instruction(SOUP) and first.success
    assert first.observations.shape == (6, 8) and first.actions.shape == (5, 7)
    np.testing.assert_array_equal(first.observations[0], [1, 1, 1, 2, 2, 2, 3, 3])
    np.testing.assert_array_equal(first.successes, [0, 0, 0, 0, 1])
    # The env's layout [T+1, V, 3, H, W], upright (the files hold robosuite's rotated frames).
    assert first.images.shape == (6, 2, 3, 6, 6)
    np.testing.assert_array_equal(first.images[:5, 0], frames[0][:, ::-1, ::-1].transpose(0, 3, 1, 2))
    np.testing.assert_array_equal(first.images[:5, 1], frames[1][:, ::-1, ::-1].transpose(0, 3, 1, 2))
    chunks = demos_to_chunks(demos, [SOUP], horizon=3, images=True)
    assert chunks["obs"]["image"].shape == (10, 2, 3, 6, 6) and chunks["actions"].shape == (10, 3, 7)
    assert load_dataset(tmp_path)[0].images is None  # frames only for the cameras asked for
    assert load_dataset(tmp_path, ["agentview"], image_size=3)[0].images.shape == (6, 1, 3, 3, 3)  # resized


def _png(image: np.ndarray) -> bytes:
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    return buffer.getvalue()


@pytest.mark.parametrize("version", ["v2.1", "v3.0"])
def test_lerobot_loader(tmp_path, version):
    import pyarrow as pa
    import pyarrow.parquet as pq

    rng = np.random.default_rng(1)
    goal = next(t for t in all_tasks().values() if t.instruction != t.bddl_instruction().lower())
    instructions = ["Pick up the alphabet soup and place it in the basket.", goal.bddl_instruction()]
    rows = []
    for episode, (task_index, length) in enumerate([(0, 4), (1, 3)]):
        for frame in range(length):
            rows.append({"observation.state": [float(episode), frame, 0, 0, 0, 0, 0, 0],
                         "action": [float(frame)] * 7, "episode_index": episode, "frame_index": frame,
                         "task_index": task_index, "index": len(rows),
                         "observation.images.image": {"bytes": _png(rng.integers(0, 256, (4, 4, 3), dtype=np.uint8)),
                                                      "path": None}})
    shuffled = [rows[i] for i in rng.permutation(len(rows))]  # order comes from the indices
    (tmp_path / "meta").mkdir()
    (tmp_path / "data" / "chunk-000").mkdir(parents=True)
    features = {"observation.state": {"dtype": "float32", "shape": [8]}, "action": {"dtype": "float32", "shape": [7]},
                "observation.images.image": {"dtype": "image", "shape": [4, 4, 3]}}
    (tmp_path / "meta" / "info.json").write_text(json.dumps({"codebase_version": version, "fps": 20,
                                                             "features": features}))
    if version == "v2.1":
        (tmp_path / "meta" / "tasks.jsonl").write_text(
            "\n".join(json.dumps({"task_index": i, "task": t}) for i, t in enumerate(instructions)))
        for episode in (0, 1):
            table = pa.Table.from_pylist([r for r in shuffled if r["episode_index"] == episode])
            pq.write_table(table, tmp_path / "data" / "chunk-000" / f"episode_{episode:06d}.parquet")
    else:
        pq.write_table(pa.table({"task_index": [0, 1], "__index_level_0__": instructions}),
                       tmp_path / "meta" / "tasks.parquet")
        pq.write_table(pa.Table.from_pylist(shuffled), tmp_path / "data" / "chunk-000" / "file-000.parquet")
    demos = load_demos(tmp_path, get_simulator("libero"), cameras=["agentview"], image_size=4)
    assert [d.task for d in demos] == [SOUP, goal.name]
    assert demos[1].instruction == goal.instruction  # the benchmark's wording, whatever the dataset's
    np.testing.assert_array_equal(demos[0].actions[:, 0], [0, 1, 2, 3])
    np.testing.assert_array_equal(demos[1].observations[:, 0], [1, 1, 1, 1])
    assert demos[0].images.shape == (5, 1, 3, 4, 4)
    first = next(r for r in rows if r["episode_index"] == 0 and r["frame_index"] == 0)
    from PIL import Image
    import io

    np.testing.assert_array_equal(demos[0].images[0, 0].transpose(1, 2, 0),
                                  np.asarray(Image.open(io.BytesIO(first["observation.images.image"]["bytes"]))))
    with pytest.raises(ValueError, match="no robot0_eye_in_hand images"):
        load_demos(tmp_path, get_simulator("libero"), cameras=["robot0_eye_in_hand"])


@pytest.mark.slow
def test_tiny_sft_and_stepnft_run_and_eval_from_the_cli(tmp_path, demo_dir, capsys):
    """The camera policy of configs/libero.yaml, shrunk: SFT from a LIBERO HDF5 file, one
    π-StepNFT iteration (progress labels on the shaped reward), evaluation, then `stepnft eval`
    with a video."""
    run = tmp_path / "run"
    common = ["--env.tasks", SOUP, "--env.envs-per-task", "1", "--env.max-episode-steps", "24"]
    assert main(["train", "--config", "configs/libero.yaml", "--run-dir", str(run), *common, "--env.num-workers", "0",
                 "--env.image-size", "16", "--policy.image-size", "16", "--demos.path", str(demo_dir),
                 "--demos.episodes", "1", "--sft.steps", "3", "--sft.batch-size", "8", "--iterations", "1",
                 "--episodes-per-iteration", "1", "--eval.episodes", "1", "--eval.every", "0",
                 "--algo.minibatch-size", "8", "--env.reward", "shaped", "--algo.labels", "progress"]) == 0
    assert "reward: shaped" in (run / "config.yaml").read_text()
    summary = json.loads((run / "summary.json").read_text())
    assert summary["env_steps"] > 0 and SOUP in summary["tasks"] and (run / "policy" / "model.safetensors").is_file()
    videos = tmp_path / "videos"
    assert main(["eval", "--policy", str(run / "policy"), "--env.name", "libero", *common, "--env.image-size", "16",
                 "--eval.episodes", "2", "--video-dir", str(videos), "--out", str(tmp_path / "eval.json")]) == 0
    result = json.loads((tmp_path / "eval.json").read_text())
    assert result["tasks"][SOUP]["episodes"] == 2 and len(result["tasks"][SOUP]["ci95"]) == 2
    assert len(list(videos.glob(f"{SOUP}_ep0_*.mp4"))) == 1
