"""Evaluation: Wilson intervals, determinism on fixed initial states, rollout videos."""

import math

import numpy as np
import pytest
import torch

from stepnft.rollout.plan import RolloutSpec
from stepnft.envs.base import RenderingError
from stepnft.envs.metaworld import MetaWorld, make_metaworld_vec_env
from stepnft.evaluate import evaluate_policy, format_table, record_videos, wilson_interval
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.rollout.collector import Collector

GOAL, HAND = slice(36, 39), slice(0, 3)


class GoalSeeker(FlowPolicy):
    """A random flow policy steered toward the reach goal: whether an episode succeeds depends
    on its initial state and on the sampler's noise."""

    def sample(self, obs, noise_level=0.0, generator=None, stochastic_steps="all", keep_path=False, **kwargs):
        out = super().sample(obs, noise_level, generator, stochastic_steps, keep_path, **kwargs)
        state = obs["state"]
        out.actions[..., :3] += 10.0 * (state[:, None, GOAL] - state[:, None, HAND])
        return out


def goal_seeker() -> GoalSeeker:
    torch.manual_seed(0)
    return GoalSeeker(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1, state_clip=100.0))


def wilson_by_quadratic(k: int, n: int, z: float) -> tuple[float, float]:
    """The interval's ends are the p with |k/n - p| = z sqrt(p (1 - p) / n): roots of a quadratic."""
    p_hat = k / n
    a, b, c = n + z**2, -(2 * n * p_hat + z**2), n * p_hat**2
    root = math.sqrt(b**2 - 4 * a * c)
    return (-b - root) / (2 * a), (-b + root) / (2 * a)


@pytest.mark.parametrize("k, n", [(0, 10), (10, 10), (5, 10), (50, 100), (3, 7), (97, 100)])
def test_wilson_interval_on_known_counts(k, n):
    lo, hi = wilson_interval(k, n)
    assert (lo, hi) == pytest.approx(wilson_by_quadratic(k, n, 1.96), abs=1e-12)
    assert 0 <= lo <= k / n <= hi <= 1
    stats = pytest.importorskip("scipy.stats")
    ci = stats.binomtest(k, n).proportion_ci(method="wilson")
    assert wilson_interval(k, n, z=stats.norm.ppf(0.975)) == pytest.approx((ci.low, ci.high), abs=1e-12)


def test_wilson_interval_known_values():
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.27754), abs=1e-5)
    assert wilson_interval(5, 10) == pytest.approx((0.23659, 0.76341), abs=1e-5)
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_evaluation_depends_only_on_the_policy_and_the_eval_seed():
    policy = goal_seeker()
    venv = make_metaworld_vec_env(["reach-v3"], 2, max_episode_steps=36, seed=0)
    reset_seeds = []
    send = venv.send_ops
    venv.send_ops = lambda ops: (reset_seeds.extend(arg for _, op, arg in ops if op == "reset"), send(ops))[1]

    first = evaluate_policy(policy, venv, episodes=5, seed=3)
    # Episode e starts from state seed + e, and no spare episode is played.
    assert sorted(reset_seeds) == [3, 4, 5, 6, 7]
    assert first["tasks"]["reach-v3"]["episodes"] == 5
    assert 0 < first["tasks"]["reach-v3"]["successes"] < 5, "the check below needs mixed outcomes"

    # Training episodes in between change nothing.
    Collector(venv, seed=1).collect(policy, 4, RolloutSpec(0.2))
    again = evaluate_policy(policy, venv, episodes=5, seed=3)
    other_venv = make_metaworld_vec_env(["reach-v3"], 2, max_episode_steps=36, seed=12345)
    fresh = evaluate_policy(policy, other_venv, episodes=5, seed=3)
    # Each episode's outcome depends on its seed alone: another layout gives the same result.
    wide_venv = make_metaworld_vec_env(["reach-v3"], 5, max_episode_steps=36, seed=7)
    wide = evaluate_policy(policy, wide_venv, episodes=5, seed=3)
    assert wide == first
    wide_venv.close()
    assert first == again == fresh
    assert "reach-v3" in format_table(first, fresh)
    venv.close()
    other_venv.close()


def test_initial_states_depend_only_on_the_reset_seeds():
    a = make_metaworld_vec_env(["reach-v3", "push-v3"], 2, seed=0)
    b = make_metaworld_vec_env(["reach-v3", "push-v3"], 2, seed=99)
    unseeded_a = a.reset()[0]["state"]
    unseeded_b = b.reset()[0]["state"]
    assert not np.array_equal(unseeded_a, unseeded_b)  # the construction seeds do matter...
    seeds = [0, 1, 0, 1]
    obs_a = a.reset(seed=seeds)[0]["state"]
    obs_b = b.reset(seed=seeds)[0]["state"]
    np.testing.assert_array_equal(obs_a, obs_b)  # ...but not once the resets are seeded
    assert not np.array_equal(obs_a[0, GOAL], obs_a[1, GOAL])
    a.close()
    b.close()


def test_record_videos_writes_one_frame_per_env_step(tmp_path, monkeypatch):
    import imageio.v3 as iio

    monkeypatch.setenv("MUJOCO_GL", "egl")
    try:
        paths = record_videos(goal_seeker(), MetaWorld(), ["reach-v3"], tmp_path / "videos", seed=0, episodes=1,
                              max_episode_steps=10, size=(64, 64))
    except RenderingError as err:
        pytest.skip(f"no offscreen rendering here (EGL): {err}")
    assert paths == [tmp_path / "videos" / "reach-v3_ep0_fail.mp4"]  # 10 steps cannot reach the goal
    frames = list(iio.imiter(paths[0]))
    assert len(frames) == 1 + 10  # the reset, then every env step
    assert frames[0].shape == (64, 64, 3) and frames[-1].std() > 0
    assert sorted(p.name for p in (tmp_path / "videos").iterdir()) == ["reach-v3_ep0_fail.mp4"]


def test_the_table_aligns_long_task_names_and_keeps_the_default_width():
    row = {"success": 1.0, "ci95": [0.3, 1.0]}
    long = format_table(None, {"tasks": {"button-press-topdown-v3": row, "reach-v3": row}, "average": 1.0})
    assert len({line.index("[") for line in long.splitlines()[1:3]}) == 1  # the CIs in one column
    short = format_table(None, {"tasks": {"reach-v3": row}, "average": 1.0})
    assert short.splitlines()[1].startswith("reach-v3" + " " * 10 + " ")  # 18 wide, as the README's tables
