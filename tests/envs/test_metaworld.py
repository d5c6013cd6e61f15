import numpy as np
import pytest

from stepnft.envs import get_simulator, make_vec_env
from stepnft.envs.metaworld import (
    INSTRUCTIONS,
    TASK_NAMES,
    MetaWorld,
    MetaWorldChunkEnv,
    instruction_for,
    make_metaworld_vec_env,
    validate_tasks,
)

# The scripted experts warn when their gains saturate an action; it is clipped anyway.
pytestmark = pytest.mark.filterwarnings("ignore:Constant:UserWarning")

OBJECT_XYZ = slice(4, 7)
GOAL_XYZ = slice(36, 39)


def expert_actions(task: str, seed: int, max_steps: int = 200) -> np.ndarray:
    """The scripted expert's actions [T, 4] for one episode, run until its first success."""
    env = MetaWorldChunkEnv(task, n_exec=1, max_episode_steps=max_steps)
    expert = MetaWorld().expert(task, seed=0)
    obs, _ = env.reset(seed=seed)
    actions, done = [], False
    while not done:
        action = np.clip(expert.act(obs), -1, 1).astype(np.float32)
        obs, _, terminated, truncated, info = env.step(action[None])
        actions.append(action)
        done = terminated or truncated
    assert info["success"], "the expert should solve reach-v3"
    return np.stack(actions)


def test_every_task_has_a_distinct_instruction():
    assert len(TASK_NAMES) == 50
    assert all(name.endswith("-v3") for name in TASK_NAMES)
    assert TASK_NAMES == sorted(INSTRUCTIONS)
    texts = [instruction_for(task) for task in TASK_NAMES]
    assert all(text.strip() for text in texts)
    assert len(set(texts)) == len(texts)


def test_mt10_mt50_and_the_difficulty_splits_match_metaworld():
    from metaworld.env_dict import MT10_V3

    from stepnft.envs.metaworld.benchmarks import DIFFICULTY, MT10, MT50, difficulty_of

    assert list(MT10) == list(MT10_V3) and list(MT50) == TASK_NAMES
    assert {k: len(v) for k, v in DIFFICULTY.items()} == {"easy": 28, "medium": 11, "hard": 6, "very_hard": 5}
    assert sorted(t for tasks in DIFFICULTY.values() for t in tasks) == TASK_NAMES  # each task once
    assert difficulty_of("shelf-place-v3") == "very_hard" and difficulty_of("reach-v3") == "easy"
    with pytest.raises(KeyError):
        difficulty_of("reach-v2")


def test_unknown_task_names_the_valid_ones():
    assert validate_tasks("reach-v3, push-v3") == ["reach-v3", "push-v3"]
    with pytest.raises(ValueError) as error:
        validate_tasks("reach-v3,foo-v3")
    message = str(error.value)
    assert message.startswith("unknown MetaWorld task 'foo-v3'; valid names: assembly-v3, basketball-v3")
    assert "window-open-v3" in message and "\n" not in message
    with pytest.raises(ValueError, match="pick-place-v2"):
        MetaWorldChunkEnv("pick-place-v2")
    with pytest.raises(ValueError, match="valid names"):
        instruction_for("pick-place-v2")


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="500"):
        MetaWorldChunkEnv("reach-v3", max_episode_steps=501)
    with pytest.raises(ValueError, match="n_exec"):
        MetaWorldChunkEnv("reach-v3", n_exec=0)
    env = MetaWorldChunkEnv("reach-v3", n_exec=4)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((4, 4)))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        env.step(np.zeros((8, 4)))
    with pytest.raises(ValueError, match="each task"):
        make_metaworld_vec_env(["reach-v3", "reach-v3"])


def test_the_simulator_interface():
    sim = get_simulator("metaworld")
    assert isinstance(sim, MetaWorld) and (sim.state_dim, sim.action_dim) == (39, 4)
    assert sim.task_names() == TASK_NAMES and sim.instruction("push-v3") == INSTRUCTIONS["push-v3"]
    with pytest.raises(ValueError, match="unknown simulator 'gazebo'; choose one of: metaworld"):
        get_simulator("gazebo")
    assert not sim.has_dataset(".")  # MetaWorld's demonstrations are stepnft's own format
    from stepnft.config import EnvConfig

    venv = make_vec_env(EnvConfig(tasks=["reach-v3"], envs_per_task=2, max_episode_steps=7), n_exec=3, seed=0)
    assert venv.num_envs == 2 and venv.single_action_space.shape == (3, 4)
    obs, _ = venv.reset(seed=[0, 1])
    assert set(obs) == {"state"} and obs["state"].shape == (2, 39)
    venv.close()


def test_seeded_reset_depends_only_on_task_and_seed():
    env = MetaWorldChunkEnv("pick-place-v3", seed=123)
    first, info = env.reset(seed=5)
    assert set(first) == {"state"}
    first = first["state"]
    assert first.shape == (39,) and first.dtype == np.float32
    assert info == {"success": False, "steps": 0, "episode_steps": 0}
    rng = np.random.default_rng(0)
    for _ in range(5):
        env.step(rng.uniform(-1, 1, size=(4, 4)))
    env.reset(seed=6)
    env.reset()
    env.step(rng.uniform(-1, 1, size=(4, 4)))
    again = env.reset(seed=5)[0]["state"]
    np.testing.assert_array_equal(first, again)

    fresh = MetaWorldChunkEnv("pick-place-v3", seed=999).reset(seed=5)[0]["state"]
    np.testing.assert_array_equal(first, fresh)

    other = env.reset(seed=6)[0]["state"]
    assert not np.allclose(first[OBJECT_XYZ], other[OBJECT_XYZ])
    assert not np.allclose(first[GOAL_XYZ], other[GOAL_XYZ])


def test_unseeded_resets_follow_the_construction_seed():
    a = MetaWorldChunkEnv("push-v3", seed=7)
    b = MetaWorldChunkEnv("push-v3", seed=7)
    a_states = [a.reset()[0]["state"] for _ in range(3)]
    b_states = [b.reset()[0]["state"] for _ in range(3)]
    np.testing.assert_array_equal(np.stack(a_states), np.stack(b_states))
    assert not np.allclose(a_states[0][GOAL_XYZ], a_states[1][GOAL_XYZ])
    c_state = MetaWorldChunkEnv("push-v3", seed=8).reset()[0]["state"]
    assert not np.allclose(a_states[0][GOAL_XYZ], c_state[GOAL_XYZ])


def test_chunks_run_until_truncation_then_step_is_a_no_op():
    env = MetaWorldChunkEnv("reach-v3", n_exec=4, max_episode_steps=10)
    env.reset(seed=0)
    chunk = np.full((4, 4), 0.5, dtype=np.float32)
    results = [env.step(chunk) for _ in range(3)]
    assert [info["steps"] for *_, info in results] == [4, 4, 2]
    assert [info["episode_steps"] for *_, info in results] == [4, 8, 10]
    assert [truncated for _, _, _, truncated, _ in results] == [False, False, True]
    assert not any(terminated for _, _, terminated, _, _ in results)

    last_obs = results[-1][0]["state"]
    obs, reward, terminated, truncated, info = env.step(chunk)
    np.testing.assert_array_equal(obs["state"], last_obs)
    assert (reward, terminated, truncated) == (0.0, False, True)
    assert info == {"success": False, "steps": 0, "episode_steps": 10}


@pytest.mark.parametrize("terminate_on_success", [True, False])
def test_success_ends_the_chunk_early(terminate_on_success):
    actions = expert_actions("reach-v3", seed=0)
    success_step = len(actions)  # the expert episode stops at its first success
    # Pad to whole chunks of 4 with a few extra zero actions after the success step.
    padded = np.concatenate([actions, np.zeros((8 - success_step % 4, 4), np.float32)])
    env = MetaWorldChunkEnv("reach-v3", n_exec=4, terminate_on_success=terminate_on_success)
    env.reset(seed=0)
    results = [env.step(chunk) for chunk in padded.reshape(-1, 4, 4)]
    calls_before_success = (success_step - 1) // 4
    for _, _, terminated, _, info in results[:calls_before_success]:
        assert not terminated and not info["success"]
    _, _, terminated, truncated, info = results[calls_before_success]
    assert info["success"] and not truncated
    if terminate_on_success:
        assert terminated
        assert info["steps"] == success_step - 4 * calls_before_success
        assert info["episode_steps"] == success_step
        # Later calls are no-ops that repeat the outcome.
        _, reward, terminated, _, info = results[-1]
        assert terminated and info["success"] and reward == 0.0 and info["steps"] == 0
    else:
        assert not terminated and info["steps"] == 4
        _, _, terminated, _, info = results[-1]
        assert not terminated and info["success"] and info["episode_steps"] == len(padded)


def test_vec_env_layout_and_distinct_sub_env_seeds():
    vec = make_metaworld_vec_env("reach-v3,push-v3", envs_per_task=2, n_exec=2, seed=0)
    assert vec.num_envs == 4
    assert vec.tasks == ["reach-v3", "push-v3"]
    assert vec.task_names == ["reach-v3", "reach-v3", "push-v3", "push-v3"]
    assert vec.task_ids.dtype == np.int64 and vec.task_ids.tolist() == [0, 0, 1, 1]
    assert vec.instructions == [instruction_for("reach-v3"), instruction_for("push-v3")]
    assert vec.action_space.shape == (4, 2, 4)
    obs = vec.reset()[0]["state"]
    assert obs.shape == (4, 39) and obs.dtype == np.float32
    assert not np.allclose(obs[0, GOAL_XYZ], obs[1, GOAL_XYZ])
    assert not np.allclose(obs[2, GOAL_XYZ], obs[3, GOAL_XYZ])
    other_vec = make_metaworld_vec_env("reach-v3,push-v3", envs_per_task=2, seed=1)
    other = other_vec.reset()[0]["state"]
    assert not np.allclose(obs[:, GOAL_XYZ], other[:, GOAL_XYZ])
    vec.close()
    other_vec.close()


@pytest.mark.parametrize("num_workers", [0, 2])
def test_waves_give_chosen_states_and_tolerate_finished_envs(num_workers):
    vec = make_metaworld_vec_env(["reach-v3", "push-v3"], envs_per_task=2, n_exec=4, max_episode_steps=6,
                                 num_workers=num_workers)
    seeds = [11, 12, 13, 14]
    initial = vec.reset(seed=seeds)[0]["state"]
    for i, (task, seed) in enumerate(zip(vec.task_names, seeds)):
        single = MetaWorldChunkEnv(task).reset(seed=seed)[0]["state"]
        np.testing.assert_array_equal(initial[i], single)

    chunk = np.full((4, 4, 4), 0.3, dtype=np.float32)
    vec.step(chunk)
    last_obs, _, _, truncated, info = vec.step(chunk)
    assert truncated.all() and info["episode_steps"].tolist() == [6] * 4
    obs, reward, _, truncated, info = vec.step(chunk)
    np.testing.assert_array_equal(obs["state"], last_obs["state"])
    assert truncated.all() and (reward == 0).all() and (info["steps"] == 0).all()

    states = vec.rng_state()
    unseeded = vec.reset()[0]["state"]
    vec.set_rng_state(states)  # a checkpoint's env streams continue exactly
    np.testing.assert_array_equal(vec.reset()[0]["state"], unseeded)

    again = vec.reset(seed=seeds)[0]["state"]
    np.testing.assert_array_equal(again, initial)
    vec.close()
