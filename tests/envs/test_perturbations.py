"""Perturbations: each changes what it claims and nothing else, held-out values are never
training values, and an episode's perturbation depends only on its reset seed."""

import numpy as np
import pytest

from stepnft.envs.base import RenderingError
from stepnft.envs.metaworld import MetaWorld, MetaWorldChunkEnv
from stepnft.envs.metaworld.instructions import INSTRUCTIONS, PARAPHRASES
from stepnft.envs.metaworld.perturb import MODEL_FIELDS
from stepnft.envs.perturbations import (FAMILY, HELDOUT_DISTRACTORS, RANGES, SUITES, TRAIN_DISTRACTORS, Perturbations,
                                        draw, draw_color, expand, hue_bin)

pytestmark = pytest.mark.filterwarnings("ignore:Constant:UserWarning")

SEED = 11
ACTIONS = np.random.default_rng(0).uniform(-1, 1, (3, 4, 4)).astype(np.float32)

# What each perturbation changes: model arrays, the initial state, the trajectory under fixed
# actions, the images, the instruction. Everything else must stay exactly as without it.
CLAIMS = {
    "table_color": {"geom_rgba", "image"},
    "floor_color": {"geom_rgba", "image"},
    "object_color": {"geom_rgba", "image"},
    "lighting": {"light_diffuse", "light_specular", "headlight", "image"},
    "camera_pose": {"cam_pos", "cam_quat", "image"},
    "paraphrase": {"instruction"},
    "distractor": {"instruction"},
    "object_position": {"initial_state", "trajectory", "image"},
    "action_noise": {"trajectory"},
    # The puck also settles on the table under the new physics during MetaWorld's reset (< 1 mm).
    "friction": {"geom_friction", "initial_state", "trajectory"},
    "mass": {"body_mass", "body_inertia", "initial_state", "trajectory"},
}
CONSEQUENCES = {"action_noise": {"image"}, "friction": {"image"}, "mass": {"image"}}
"""What may follow from a changed trajectory: the robot and puck move in the images too."""

def observe(env: MetaWorldChunkEnv) -> dict:
    """Everything a perturbation could touch, after a seeded reset and three fixed chunks."""
    m = env._sim.model
    obs, _ = env.reset(seed=SEED)
    seen = {name: getattr(m, name).copy() for name in MODEL_FIELDS}
    seen["headlight"] = np.concatenate([m.vis.headlight.diffuse, m.vis.headlight.specular])
    seen["initial_state"] = obs["state"]
    seen["instruction"] = np.asarray(obs.get("instruction", 0))
    steps = [env.step(a)[0] for a in ACTIONS]
    seen["trajectory"] = np.stack([o["state"] for o in steps])
    seen["image"] = np.stack([obs["image"]] + [o["image"] for o in steps])
    return seen


def push_env(**kwargs) -> MetaWorldChunkEnv:
    try:
        return MetaWorldChunkEnv("push-v3", cameras=["corner"], image_size=16, max_episode_steps=12, **kwargs)
    except RenderingError as err:
        pytest.skip(f"no offscreen rendering here (EGL): {err}")


@pytest.fixture(scope="module")
def nominal():
    env = push_env()
    yield observe(env)
    env.close()


@pytest.mark.parametrize("name", list(CLAIMS))
def test_each_perturbation_changes_what_it_claims_and_nothing_else(name, nominal):
    assert set(CLAIMS) == set(FAMILY)
    env = push_env(perturbations=Perturbations((name,), heldout=True))
    seen = observe(env)
    changed = {key for key in nominal if not np.array_equal(nominal[key], seen[key])}
    assert CLAIMS[name] <= changed <= CLAIMS[name] | CONSEQUENCES.get(name, set())
    m, p = env._sim.model, env.episode_perturbations[name]
    if name.endswith("_color"):
        rows = np.flatnonzero((nominal["geom_rgba"] != seen["geom_rgba"]).any(1))
        np.testing.assert_array_equal(rows, env._perturber.geoms[name])  # those geoms, and all of them
        np.testing.assert_allclose(m.geom_rgba[rows, :3], np.broadcast_to(p["rgb"], (len(rows), 3)), atol=1e-6)
    if name == "friction":
        np.testing.assert_allclose(m.geom_friction[:, 0], nominal["geom_friction"][:, 0] * p["factor"], rtol=1e-6)
        np.testing.assert_array_equal(m.geom_friction[:, 1:], nominal["geom_friction"][:, 1:])
    if name == "mass":
        moved = np.flatnonzero(nominal["body_mass"] != seen["body_mass"])
        assert [m.body(b).name for b in moved] == ["obj"]  # push-v3's puck, not the robot or the table
        np.testing.assert_allclose(m.body_mass[moved], nominal["body_mass"][moved] * p["factor"], rtol=1e-6)
    if name == "object_position":
        space = env._sim._random_reset_space
        obj, goal = seen["initial_state"][4:7], seen["initial_state"][36:39]
        for xyz, low, high in ((obj, space.low[:3], space.high[:3]), (goal, space.low[3:], space.high[3:])):
            assert ((xyz[:2] < low[:2] - 1e-6) | (xyz[:2] > high[:2] + 1e-6)).any()  # outside the training range
    if name in ("paraphrase", "distractor"):
        text = env.instructions[int(seen["instruction"])]
        held = PARAPHRASES["push-v3"]["heldout"] if name == "paraphrase" else [
            t.format(INSTRUCTIONS["push-v3"]) for t in HELDOUT_DISTRACTORS]
        assert text in held
    env.close()


def test_the_nominal_model_is_restored_between_episodes():
    env = push_env(perturbations=Perturbations(("vision", "execution")))  # training: all at once
    seen = observe(env)
    again = observe(env)  # same seed: the edits of the first episode did not accumulate
    for key in seen:
        np.testing.assert_array_equal(seen[key], again[key])
    first = env.episode_perturbations
    env.reset(seed=SEED + 1)
    assert env.episode_perturbations["lighting"] != first["lighting"]
    env.close()


def test_object_positions_stay_outside_the_training_range_for_the_default_tasks():
    for task in ("reach-v3", "push-v3", "pick-place-v3", "door-open-v3", "drawer-open-v3"):
        env = MetaWorldChunkEnv(task, perturbations=Perturbations(("object_position",), heldout=True))
        low, high = env._sim._random_reset_space.low, env._sim._random_reset_space.high
        for seed in range(10):
            env.reset(seed=seed)
            vec = env._sim._last_rand_vec
            for block in range(0, len(low), 3):
                xy = slice(block, block + 2)
                if (high[xy] > low[xy]).any():
                    assert ((vec[xy] < low[xy]) | (vec[xy] > high[xy])).any(), (task, seed)
            np.testing.assert_array_equal(vec[2::3], np.clip(vec[2::3], low[2::3], high[2::3]))  # heights unchanged
        env.close()


def test_training_and_heldout_values_never_meet():
    rng = np.random.default_rng(0)
    for key, (train, heldout) in RANGES.items():
        for lo, hi in train:
            assert all(hi < h_lo or lo > h_hi for h_lo, h_hi in heldout), key
        values = [draw(rng, key, False) for _ in range(300)], [draw(rng, key, True) for _ in range(300)]
        for split, intervals in zip(values, (train, heldout)):
            assert all(any(lo <= v <= hi for lo, hi in intervals) for v in split), key
    train_bins = {hue_bin(draw_color(rng, False)) for _ in range(300)}
    held_bins = {hue_bin(draw_color(rng, True)) for _ in range(300)}
    assert train_bins == set(range(0, 12, 2)) and held_bins == set(range(1, 12, 2))
    assert not set(TRAIN_DISTRACTORS) & set(HELDOUT_DISTRACTORS)
    train_texts = {t for p in PARAPHRASES.values() for t in p["train"]}
    for task, p in PARAPHRASES.items():
        assert len(p["heldout"]) >= 4 and not set(p["heldout"]) & (train_texts | set(INSTRUCTIONS.values())), task


def test_episode_perturbations_depend_only_on_the_seed():
    spec = Perturbations(("execution",), heldout=True)
    env, other = (MetaWorldChunkEnv("reach-v3", perturbations=spec, seed=s) for s in (0, 1))
    env.reset(seed=7)
    first = env.episode_perturbations
    env.reset()
    env.reset(seed=3)
    other.reset(seed=7)
    assert repr(other.episode_perturbations) == repr(first)
    # A suite cycles through its perturbations with the episode seed: equal shares.
    names = []
    for seed in range(8):
        env.reset(seed=seed)
        names += list(env.episode_perturbations)
    assert names == [spec.pick(s) for s in range(8)] == list(SUITES["execution"]) * 2
    env.close()
    other.close()


def test_names_and_config_checks():
    assert expand("vision") == SUITES["vision"] and expand(["friction", "execution"])[0] == "friction"
    with pytest.raises(ValueError, match="unknown perturbation 'fog'; choose suites or perturbations among: vision"):
        expand(["fog"])
    from stepnft.config import EnvConfig

    assert EnvConfig(randomize=["semantic,friction"]).randomize == ["paraphrase", "distractor", "friction"]
    with pytest.raises(ValueError, match="set env.cameras"):
        EnvConfig(randomize=["lighting"])
    with pytest.raises(ValueError, match="semantic perturbations need MetaWorld"):
        from stepnft.envs.bandit import Bandit

        Bandit().instruction_variants("bandit", Perturbations(("paraphrase",)))
    # Every task has its variants: the canonical instruction first, then held-out paraphrases and distractors.
    variants = MetaWorld().instruction_variants("door-open-v3", Perturbations(("semantic",), heldout=True))
    assert variants[0] == INSTRUCTIONS["door-open-v3"] and len(variants) == 1 + 8 + len(HELDOUT_DISTRACTORS)
