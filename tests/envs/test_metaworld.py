import numpy as np
import pytest
from metaworld.policies import ENV_POLICY_MAP

from stepnft.envs.instructions import INSTRUCTIONS, instruction_for
from stepnft.envs.metaworld import (
    TASK_NAMES,
    MetaWorldChunkEnv,
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
    expert = ENV_POLICY_MAP[task]()
    obs, _ = env.reset(seed=seed)
    actions, done = [], False
    while not done:
        action = np.clip(expert.get_action(obs), -1, 1).astype(np.float32)
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


def test_seeded_reset_depends_only_on_task_and_seed():
    env = MetaWorldChunkEnv("pick-place-v3", seed=123)
    first, info = env.reset(seed=5)
    assert first.shape == (39,) and first.dtype == np.float32
    assert info == {"success": False, "steps": 0, "episode_steps": 0}
    rng = np.random.default_rng(0)
    for _ in range(5):
        env.step(rng.uniform(-1, 1, size=(4, 4)))
    env.reset(seed=6)
    env.reset()
    env.step(rng.uniform(-1, 1, size=(4, 4)))
    again, _ = env.reset(seed=5)
    np.testing.assert_array_equal(first, again)

    fresh, _ = MetaWorldChunkEnv("pick-place-v3", seed=999).reset(seed=5)
    np.testing.assert_array_equal(first, fresh)

    other, _ = env.reset(seed=6)
    assert not np.allclose(first[OBJECT_XYZ], other[OBJECT_XYZ])
    assert not np.allclose(first[GOAL_XYZ], other[GOAL_XYZ])


def test_unseeded_resets_follow_the_construction_seed():
    a = MetaWorldChunkEnv("push-v3", seed=7)
    b = MetaWorldChunkEnv("push-v3", seed=7)
    a_states = [a.reset()[0] for _ in range(3)]
    b_states = [b.reset()[0] for _ in range(3)]
    np.testing.assert_array_equal(np.stack(a_states), np.stack(b_states))
    assert not np.allclose(a_states[0][GOAL_XYZ], a_states[1][GOAL_XYZ])
    c_state, _ = MetaWorldChunkEnv("push-v3", seed=8).reset()
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

    last_obs = results[-1][0]
    obs, reward, terminated, truncated, info = env.step(chunk)
    np.testing.assert_array_equal(obs, last_obs)
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
    obs, _ = vec.reset()
    assert obs.shape == (4, 39) and obs.dtype == np.float32
    assert not np.allclose(obs[0, GOAL_XYZ], obs[1, GOAL_XYZ])
    assert not np.allclose(obs[2, GOAL_XYZ], obs[3, GOAL_XYZ])
    other, _ = make_metaworld_vec_env("reach-v3,push-v3", envs_per_task=2, seed=1).reset()
    assert not np.allclose(obs[:, GOAL_XYZ], other[:, GOAL_XYZ])
    vec.close()


def test_same_step_autoreset_keeps_the_finished_episodes_success():
    # Sub-env 0 replays the expert (succeeds); sub-env 1 idles until truncation.
    actions = expert_actions("reach-v3", seed=0)
    max_steps = len(actions) + 5
    vec = make_metaworld_vec_env("reach-v3", envs_per_task=2, n_exec=1, max_episode_steps=max_steps)
    vec.reset(seed=[0, 1])
    for t in range(max_steps):
        batch = np.zeros((2, 1, 4), dtype=np.float32)
        if t < len(actions):
            batch[0, 0] = actions[t]
        obs, _, terminated, truncated, info = vec.step(batch)
        ended = terminated | truncated
        if t == len(actions) - 1:
            assert ended.tolist() == [True, False]
            assert info["_final_info"].tolist() == [True, False]
            assert info["final_info"]["success"][0]
            assert info["final_info"]["episode_steps"][0] == len(actions)
            # The top level already describes the next episode of sub-env 0.
            assert not info["success"][0] and info["episode_steps"][0] == 0
        elif t == max_steps - 1:
            assert truncated[1] and info["_final_info"][1]
            assert not info["final_info"]["success"][1]
        else:
            assert not ended.any()
    vec.close()


def test_disabled_autoreset_gives_chosen_states_and_tolerates_finished_envs():
    vec = make_metaworld_vec_env(
        ["reach-v3", "push-v3"], envs_per_task=2, n_exec=4, max_episode_steps=6, autoreset=False
    )
    seeds = [11, 12, 13, 14]
    initial, _ = vec.reset(seed=seeds)
    for i, (task, seed) in enumerate(zip(vec.task_names, seeds)):
        single, _ = MetaWorldChunkEnv(task).reset(seed=seed)
        np.testing.assert_array_equal(initial[i], single)

    chunk = np.full((4, 4, 4), 0.3, dtype=np.float32)
    vec.step(chunk)
    last_obs, _, _, truncated, info = vec.step(chunk)
    assert truncated.all() and info["episode_steps"].tolist() == [6] * 4
    obs, reward, _, truncated, info = vec.step(chunk)
    np.testing.assert_array_equal(obs, last_obs)
    assert truncated.all() and (reward == 0).all() and (info["steps"] == 0).all()

    again, _ = vec.reset(seed=seeds)
    np.testing.assert_array_equal(again, initial)
    vec.close()
