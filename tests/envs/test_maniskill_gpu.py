"""ManiSkill's GPU-parallel physics behind the vector env interface (``env.sim_backend: gpu``).

No GPU here: the batched env is a stand-in that follows ManiSkill's batched API (obs, reward
and success as ``[N]``-batched tensors, partial resets by ``options["env_idx"]``, one torch seed
per reset call for the scenes it resets, sensors that capture every scene at once). The GPU
vector env over it must give the collector the very batch the CPU backend's chunk envs give
over the same stand-in at one scene each."""

from functools import partial

import numpy as np
import pytest
import torch

try:
    from stepnft.envs.maniskill import ManiSkill
    from stepnft.envs.maniskill import env as maniskill_env
    from stepnft.envs.maniskill.gpu import ManiSkillGPUVecEnv
except ImportError as err:
    pytest.skip(f"the ManiSkill extra is not installed: {err}", allow_module_level=True)

from stepnft.config import EnvConfig
from stepnft.envs.base import ChunkVecEnv
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.rollout.collector import Collector
from stepnft.rollout.plan import RolloutSpec
from stepnft.settings import SettingError

TASKS = ["PushCube-v1", "PickCube-v1"]
OBS_DIM = 12


class _Sensor:
    def __init__(self, env):
        self.env, self.frame = env, None

    def capture(self):
        self.frame = self.env.pos.clone()

    def get_obs(self, rgb=True, depth=False, position=False, segmentation=False):
        # [N, H, W, 3]: a picture of each scene's position, as ManiSkill's batched sensors return
        values = ((self.frame[:, :3] + 1.0) * 100.0).clamp(0, 255).to(torch.uint8)
        return {"rgb": values[:, None, None, :].expand(-1, 8, 8, 3).clone()}


class _Scene:
    def update_render(self, update_sensors=True, update_human_render_cameras=False):
        pass


class FakeBatchedManiSkill:
    """A stand-in for ``gym.make(task, num_envs=N, ...)``: a point moved by the actions'
    translation; success once its x passes 0.12 (the task shifts the start)."""

    def __init__(self, task, num_envs=1, **kwargs):
        self.unwrapped, self.num_envs, self.device, self.kwargs = self, num_envs, torch.device("cpu"), kwargs
        self.offset = 0.02 * TASKS.index(task)
        self.pos = torch.zeros(num_envs, 3)
        self.t = torch.zeros(num_envs)
        self._sensors = {"base_camera": _Sensor(self)}
        self._hidden_objects = []
        self.scene = _Scene()
        self.resets = []

    def reset(self, seed=None, options=None):
        idx = (options or {}).get("env_idx", torch.arange(self.num_envs))
        self.resets.append(len(idx))
        first = seed[0] if isinstance(seed, list) else seed
        generator = torch.Generator().manual_seed(int(first))  # one seed per call, as ManiSkill's torch.manual_seed
        self.pos[idx] = torch.rand(len(idx), 3, generator=generator) * 0.2 - 0.1 + self.offset
        self.t[idx] = 0
        return self._obs(), {}

    def step(self, action):
        action = torch.as_tensor(action, dtype=torch.float32).reshape(self.num_envs, 7)
        self.pos = self.pos + 0.04 * action[:, :3]
        self.t += 1
        success = self.pos[:, 0] > 0.12
        return self._obs(), -self.pos[:, 0].abs(), torch.zeros_like(success), torch.zeros_like(success), \
            {"success": success}

    def _obs(self):
        return torch.cat([self.pos, self.t[:, None], torch.zeros(self.num_envs, OBS_DIM - 4)], dim=1)

    def close(self):
        pass


def gpu_venv(envs_per_task=3, cameras=(), seed=0, **kwargs):
    layout = ManiSkill().vec_env_layout(TASKS, envs_per_task)
    return ManiSkillGPUVecEnv(layout["tasks"], layout["instructions"], layout["task_ids"], n_exec=4,
                              max_episode_steps=kwargs.pop("max_episode_steps", 20), seed=seed, cameras=cameras,
                              image_size=8, device="cpu", make=FakeBatchedManiSkill, **kwargs)


def cpu_venv(monkeypatch, envs_per_task=3, cameras=(), seed=0):
    """The CPU backend's chunk envs over the stand-in at one scene each, in one lane (as the GPU env)."""
    monkeypatch.setattr(maniskill_env, "make_maniskill_env", lambda task, **kw: FakeBatchedManiSkill(task, **kw))
    layout = ManiSkill().vec_env_layout(TASKS, envs_per_task)
    seeds = np.random.SeedSequence(seed).generate_state(len(layout["task_ids"]))
    fns = [partial(maniskill_env.ManiSkillChunkEnv, TASKS[k], n_exec=4, max_episode_steps=20, seed=int(s),
                   cameras=cameras, image_size=8) for k, s in zip(layout["task_ids"], seeds)]
    return ChunkVecEnv(fns, lanes=np.zeros(len(fns), dtype=np.int64), **layout)


def policy(cameras=()):
    torch.manual_seed(0)
    return FlowPolicy(FlowPolicyConfig(lang_dim=0, hidden_dim=16, num_layers=1, state_dim=64, action_dim=7,
                                       state_clip=100.0))


def test_the_collector_gets_the_cpu_backends_batch(monkeypatch):
    spec = RolloutSpec(0.6, record_steps="all", group_size=2)
    batches = []
    for venv in (cpu_venv(monkeypatch), gpu_venv()):
        batches.append(Collector(venv, seed=4).collect(policy(), 0, spec, task_episodes=[8, 6]))
        venv.close()
    a, b = batches
    # Some episodes succeed early (inside a chunk), some run to the cap: both paths are covered.
    assert a.episode_success.any() and not a.episode_success.all()
    assert (a.episode_length < 20).any() and (a.episode_length % 4 != 0).any()
    for key in ("episode_success", "episode_task", "episode_length", "episode_seed", "actions", "mask", "reward",
                "done", "episode", "call", "x_t", "x_next", "v_old", "t", "dt"):
        assert torch.equal(getattr(a, key), getattr(b, key)), key
    assert torch.equal(a.obs["state"], b.obs["state"])


def test_each_reset_is_one_scene_so_the_start_depends_only_on_the_seed():
    venv = gpu_venv()
    obs, info = venv.reset(seed=[5, 5, 6, 5, 7, 7])
    state = obs["state"]
    np.testing.assert_array_equal(state[0], state[1])  # same task, same seed
    assert not np.array_equal(state[0], state[2])
    np.testing.assert_array_equal(state[4], state[5])
    assert not np.array_equal(state[0], state[3])  # another task (shifted start)
    assert all(n == 1 for env in venv._envs for n in env.resets[1:])  # after the first full reset: one scene per call
    assert info["episode_steps"].tolist() == [0] * 6
    again, _ = venv.reset(seed=[6, 5, 5, 5, 7, 7])
    np.testing.assert_array_equal(again["state"][0], state[2])
    venv.close()


def test_steps_before_resets_and_the_chunk_contract():
    venv = gpu_venv(envs_per_task=2, max_episode_steps=6)
    venv.reset(seed=[0, 1, 2, 3])
    chunk = np.zeros((4, 7), np.float32)
    (r0, r1) = venv._run([(0, "step", chunk), (1, "reset", 9)])
    # The step ran 4 env steps; the reset came after them and is the state of seed 9 at t = 0.
    assert r0[4]["steps"] == 4 and r0[4]["episode_steps"] == 4 and r0[0]["state"][3] == 4
    assert r1[0]["state"][3] == 0 and r1[1] == {"success": False, "steps": 0, "episode_steps": 0}
    _, _, terminated, truncated, info = venv._run([(0, "step", chunk)])[0]
    assert (info["steps"], info["episode_steps"], truncated, terminated) == (2, 6, True, False)  # cut at the cap
    before = venv._scenes[0].obs["state"].copy()
    obs, reward, _, truncated, info = venv._run([(0, "step", np.ones((4, 7), np.float32))])[0]
    assert (reward, info["steps"], truncated) == (0.0, 0, True)  # an ended episode: a no-op
    np.testing.assert_array_equal(obs["state"], before)
    with pytest.raises(ValueError, match="shape"):
        venv._run([(1, "step", np.zeros((3, 7), np.float32))])
    with pytest.raises(ValueError, match="one op per sub-env"):
        venv._run([(1, "reset", 0), (1, "reset", 1)])
    venv.close()


def test_cameras_render_every_scene_once_per_batch(monkeypatch):
    spec = RolloutSpec(0.6, record_steps="all")
    images = []
    for venv in (cpu_venv(monkeypatch, envs_per_task=2, cameras=["base_camera"]),
                 gpu_venv(envs_per_task=2, cameras=["base_camera"])):
        obs, _ = venv.reset(seed=[1, 2, 3, 4])
        assert obs["image"].shape == (4, 1, 3, 8, 8) and obs["image"].dtype == np.uint8
        batch = Collector(venv, seed=1).collect(policy(), 0, spec, task_episodes=[2, 2])
        images.append(batch.obs["image"])
        venv.close()
    assert torch.equal(images[0], images[1])
    with pytest.raises(ValueError, match="unknown ManiSkill camera 'hand_camera'"):
        gpu_venv(cameras=["hand_camera"])


def test_the_gpu_backend_is_checked_in_one_line():
    with pytest.raises(ValueError, match="needs CUDA") if not torch.cuda.is_available() else pytest.raises(ValueError):
        ManiSkill().make_vec_env(TASKS, 2, sim_backend="gpu", num_workers=0 if not torch.cuda.is_available() else 2)
    with pytest.raises(ValueError, match="num_workers 0"):
        ManiSkill().make_vec_env(TASKS, 2, sim_backend="gpu", num_workers=2)
    with pytest.raises(SettingError, match="sim_backend"):
        EnvConfig(name="metaworld", sim_backend="gpu").check()
    with pytest.raises(SettingError, match="num_workers"):
        EnvConfig(name="maniskill", tasks=TASKS, sim_backend="gpu", num_workers=2).check()
    EnvConfig(name="maniskill", tasks=TASKS, sim_backend="gpu").check()


def test_train_and_eval_run_on_the_gpu_backend_from_the_cli(monkeypatch, tmp_path):
    """``stepnft train --env.sim-backend gpu`` end to end (SFT, rollouts, evaluation, checkpoints,
    ``stepnft eval``) over the stand-in, CUDA's presence faked for the backend's check."""
    from stepnft.cli import main

    built = []  # num_envs of every batched env built: the CPU backend's are 1, the GPU backend's envs_per_task
    monkeypatch.setattr(maniskill_env, "make_maniskill_env",
                        lambda task, **kw: built.append(kw["num_envs"]) or FakeBatchedManiSkill(task, **kw))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    common = ["--env.name", "maniskill", "--env.tasks", ",".join(TASKS), "--env.max-episode-steps", "12"]
    demos = tmp_path / "demos"
    # The stand-in is not ManiSkill's scene: keep the experts' attempts whatever they reach.
    assert main(["demos", *common, "--demos.path", str(demos), "--demos.episodes", "1",
                 "--demos.no-successful-only"]) == 0
    run = tmp_path / "run"
    gpu = ["--env.sim-backend", "gpu", "--env.num-workers", "0", "--env.envs-per-task", "3"]
    assert main(["train", "--run-dir", str(run), *common, *gpu, "--demos.path", str(demos), "--demos.episodes", "1",
                 "--demos.no-successful-only",
                 "--policy.state-dim", "64", "--policy.action-dim", "7", "--policy.hidden-dim", "16",
                 "--iterations", "2", "--episodes-per-iteration", "6", "--sft.steps", "5", "--sft.batch-size", "8",
                 "--algo.minibatch-size", "16", "--eval.episodes", "3", "--eval.every", "1",
                 "--eval.during-episodes", "2", "--num-threads", "1"]) == 0
    assert (run / "policy").is_dir() and (run / "checkpoints" / "LATEST").is_file()
    assert "sim_backend: gpu" in (run / "config.yaml").read_text() and 3 in built
    assert main(["eval", "--policy", str(run / "policy"), *common, *gpu, "--eval.episodes", "3",
                 "--out", str(tmp_path / "eval.json")]) == 0
