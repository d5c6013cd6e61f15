"""LeRobot's flow VLAs (SmolVLA, π0, π0.5) behind stepnft's policy interface (stepnft.policies.lerobot).

Runs in the LeRobot environment (`bash scripts/bootstrap.sh --lerobot`, then
`.venv-lerobot/bin/python -m pytest tests/policies/test_lerobot.py`); elsewhere the model tests
skip with the reason, and the tests that need no LeRobot check that stepnft does not import it
and that a SmolVLA folder gives one line saying what is missing. Every model test runs on a tiny
SmolVLA, π0 and π0.5 (the ``tiny_folder`` fixture; π0 / π0.5 where LeRobot builds them, 0.6).
"""

import importlib.util
import json
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch

from stepnft.envs.bandit import Bandit, BanditChunkEnv

HAVE_LEROBOT = importlib.util.find_spec("lerobot") is not None
needs_lerobot = pytest.mark.skipif(not HAVE_LEROBOT, reason="LeRobot is not installed: these tests run in the LeRobot "
                                   "environment (bash scripts/bootstrap.sh --lerobot; scripts/run-tests.sh runs them)")
IMAGE = 16
MODELS = ("smolvla", "pi0", "pi05")
PARTS = {
    # Where each model's parts live in its parameter names; whether its state projection trains
    # under a scope (π0's is in the action expert's suffix; π0.5 has none: its state is in the prompt).
    "smolvla": dict(expert="lm_expert", vlm=".vlm.", lm=".vlm.model.text_model.", vision="vision_model",
                    state_trained=lambda scope: scope != "expert"),
    "pi0": dict(expert="gemma_expert", vlm=".paligemma.", lm=".language_model.", vision="vision_tower",
                state_trained=lambda scope: True),
    "pi05": dict(expert="gemma_expert", vlm=".paligemma.", lm=".language_model.", vision="vision_tower",
                 state_trained=lambda scope: False),
}


def vlm_width(policy) -> int:
    """The width of the VLM's language model (the pooled prefix features)."""
    if policy.type == "smolvla":
        return policy.lerobot.model.vlm_with_expert.config.text_config.hidden_size
    return policy.language_model.config.hidden_size


def test_importing_stepnft_does_not_import_lerobot():
    code = ("import sys, stepnft, stepnft.cli, stepnft.train, stepnft.policies.base, stepnft.policies.lerobot, "
            "stepnft.policies.lerobot.configuration; assert 'lerobot' not in sys.modules, 'lerobot imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.skipif(HAVE_LEROBOT, reason="checks the message given where LeRobot is missing")
def test_a_smolvla_folder_without_lerobot_is_one_line(tmp_path):
    from stepnft.policies.base import load_policy

    (tmp_path / "config.json").write_text(json.dumps({"type": "smolvla", "lerobot": "lerobot"}))
    with pytest.raises(ValueError, match="policy type 'smolvla': LeRobot is not installed.*bootstrap.sh --lerobot"):
        load_policy(tmp_path)


def test_a_smolvla_folders_cameras_come_from_its_image_features(tmp_path):
    """Read without LeRobot: `cameras` (the env's views, in order) from LeRobot's
    observation.images.<name> features when the stepnft config.json does not list them."""
    from stepnft.policies.lerobot.configuration import LeRobotPolicyConfig

    features = {"observation.state": {"type": "STATE", "shape": [4]},
                "observation.images.corner": {"type": "VISUAL", "shape": [3, 64, 64]},
                "observation.images.gripperPOV": {"type": "VISUAL", "shape": [3, 64, 64]}}
    (tmp_path / "lerobot").mkdir()
    (tmp_path / "lerobot" / "config.json").write_text(json.dumps(
        {"type": "smolvla", "input_features": features, "output_features": {"action": {"type": "ACTION", "shape": [4]}},
         "chunk_size": 4, "n_action_steps": 4, "num_steps": 4}))
    (tmp_path / "config.json").write_text(json.dumps({"type": "smolvla", "lerobot": "lerobot", "train": "expert"}))
    config = LeRobotPolicyConfig.read(tmp_path)
    assert config.cameras == ["corner", "gripperPOV"] and (config.state_dim, config.action_dim) == (4, 4)
    (tmp_path / "config.json").write_text(json.dumps({"type": "smolvla", "lerobot": "lerobot", "cameras": ["topview"]}))
    assert LeRobotPolicyConfig.read(tmp_path).cameras == ["topview"]  # set by the user: kept


@pytest.mark.parametrize("key, value", [("horizon", 10**12), ("num_inference_steps", 2**40), ("lora_rank", 10**9),
                                        ("n_exec", 1.5), ("state_dim", True), ("action_dim", "4")])
def test_a_hand_edited_lerobot_config_with_a_huge_or_non_integer_count_is_one_line(tmp_path, key, value):
    """Read without LeRobot, before anything is sized from it: the count, named, with its bound."""
    from stepnft.policies.lerobot.configuration import LeRobotPolicyConfig
    from stepnft.settings import WIDTH_MAX

    (tmp_path / "config.json").write_text(json.dumps({"type": "smolvla", "lerobot": "lerobot", key: value}))
    with pytest.raises(ValueError, match=f"policy {key}=.* must be an integer <= {WIDTH_MAX}"):
        LeRobotPolicyConfig.read(tmp_path)


def test_stepnft_eval_of_a_lerobot_folder_with_a_huge_chunk_is_one_line_exit_2(tmp_path):
    (tmp_path / "pol").mkdir()
    (tmp_path / "pol" / "config.json").write_text(json.dumps({"type": "smolvla", "lerobot": "lerobot",
                                                              "horizon": 10**15}))
    done = subprocess.run([sys.executable, "-m", "stepnft.cli", "eval", "--policy", str(tmp_path / "pol"),
                           "--env.name", "bandit", "--env.max-episode-steps", "8", "--env.tasks", "bandit"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    # Without LeRobot the folder's type is refused first, in one line too.
    assert ("horizon" if HAVE_LEROBOT else "LeRobot is not installed") in done.stderr, done.stderr


# --- a bandit with a synthetic camera image (the context painted into two channels) ------------
class ImageBanditEnv(gym.Wrapper):
    """The bandit with an ``image`` uint8 [1, 3, 16, 16] observation: channel k holds context k."""

    def __init__(self, env: BanditChunkEnv):
        super().__init__(env)
        self.observation_space = gym.spaces.Dict({**env.observation_space.spaces,
                                                  "image": gym.spaces.Box(0, 255, (1, 3, IMAGE, IMAGE), np.uint8)})

    @staticmethod
    def painted(obs):
        image = np.zeros((1, 3, IMAGE, IMAGE), dtype=np.uint8)
        image[0, :2] = np.round((obs["state"][:, None, None] + 1) * 127.5).astype(np.uint8)
        return obs | {"image": image}

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return self.painted(obs), info

    def step(self, action):
        obs, *rest = self.env.step(action)
        return self.painted(obs), *rest


class ImageBandit(Bandit):
    """The image bandit as a simulator with one camera, ``synthetic``, at 16 px (``--env.cameras
    synthetic --env.image-size 16``): demonstrations with images, SFT and RL from the CLI."""

    name = "bandit-image"

    def make_env(self, task, n_exec=2, max_episode_steps=2, terminate_on_success=True, seed=0, render_size=None,
                 cameras=("synthetic",), image_size=IMAGE):
        if list(cameras) != ["synthetic"] or image_size != IMAGE:
            raise ValueError(f"the image bandit has one camera, synthetic, at {IMAGE} px")
        return ImageBanditEnv(super().make_env(task, n_exec, max_episode_steps, terminate_on_success, seed))


def raw_obs(batch: int, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    state = torch.rand(batch, 2, generator=g) * 2 - 1
    image = torch.as_tensor(np.stack([ImageBanditEnv.painted({"state": s.numpy()})["image"] for s in state]))
    return {"state": state, "task": torch.zeros(batch, dtype=torch.int64), "image": image}


def skip_without(model: str) -> None:
    if not HAVE_LEROBOT:
        pytest.skip("LeRobot is not installed")
    if model != "smolvla":
        from stepnft.policies.lerobot.pi0 import needs_patched_transformers

        if needs_patched_transformers():
            pytest.skip("π0 / π0.5 need LeRobot 0.6 (this LeRobot builds them only on its patched transformers)")


@pytest.fixture(scope="module", params=MODELS)
def tiny_folder(request, tmp_path_factory):
    """A new tiny VLA of each model for the bandit (2-d state and actions, chunks of 2, 3 denoising steps)."""
    skip_without(request.param)
    from stepnft.policies.lerobot.tiny import NewVLA, new_vla

    folder = tmp_path_factory.mktemp(request.param) / "policy"
    new_vla(NewVLA(out=str(folder), model=request.param, state_dim=2, action_dim=2, chunk_size=2, n_exec=2,
                   num_steps=3, cameras=["synthetic"], image_size=IMAGE))
    return folder


def load(folder, **settings):
    from stepnft.policies.base import load_policy

    policy = load_policy(folder)
    if settings:  # another train scope / cache setting: rebuild through the same loader
        data = json.loads((folder / "config.json").read_text()) | settings
        policy = type(policy).load_folder(folder, {k: v for k, v in data.items() if k != "type"})
    policy.processor.bind_instructions(["put every action of the chunk on the target"])
    return policy


@needs_lerobot
def test_the_ode_loop_equals_lerobots_sample_actions(tiny_folder):
    policy = load(tiny_folder)
    obs = policy.processor(raw_obs(5))
    sample = policy.sample(obs, noise_level=0.0, generator=torch.Generator().manual_seed(3))
    noise = torch.randn((5, *policy.chunk_shape), generator=torch.Generator().manual_seed(3))
    lerobot = policy.lerobot
    if policy.type != "smolvla":  # π0 / π0.5: LeRobot's predict path (its sample_actions) on the same noise
        with torch.no_grad():
            reference = lerobot.predict_action_chunk(obs, noise=noise)
        torch.testing.assert_close(sample.actions, reference, rtol=0, atol=1e-6)
        return
    images, img_masks = lerobot.prepare_images(obs)
    with torch.no_grad():
        reference = lerobot.model.sample_actions(images, img_masks, obs["observation.language.tokens"],
                                                 obs["observation.language.attention_mask"], lerobot.prepare_state(obs),
                                                 noise=noise)
    torch.testing.assert_close(sample.actions, reference, rtol=0, atol=1e-6)
    # ... and so does LeRobot's whole select path (pre-processor -> predict -> post-processor)
    with torch.no_grad():
        chunk = lerobot.predict_action_chunk(policy.processor(raw_obs(5)), noise=noise)
    torch.testing.assert_close(policy.env_actions(sample.actions), policy.processor.unnormalize_actions(chunk))


@needs_lerobot
def test_the_prefix_cache_is_unchanged_by_a_flow_sde_loop(tiny_folder):
    from stepnft.sampling import sample_chunk

    from stepnft.policies.lerobot.adapter import cache_tensors

    def tensors(cache) -> dict:  # LeRobot 0.4: {layer: {"key_states": ...}}; 0.6: a DynamicCache
        if isinstance(cache, dict):
            return {(layer, k): v for layer, kv in cache.items() for k, v in kv.items()}
        return {(layer, k): v for layer, kv in enumerate(cache_tensors(cache)) for k, v in zip("kv", kv)}

    policy = load(tiny_folder)
    with torch.no_grad():
        context = policy.encode(policy.processor(raw_obs(4)))
        before = {name: (v, v.clone()) for name, v in tensors(context.past_key_values).items()}
        sample_chunk(lambda x, t: policy.denoise(context, x, t), (4, *policy.chunk_shape), num_steps=3,
                     noise_level=0.5, generator=torch.Generator().manual_seed(0))
    after = tensors(context.past_key_values)
    assert after.keys() == before.keys()
    for name, tensor in after.items():
        original, copy = before[name]
        assert tensor is original and torch.equal(tensor, copy), name


@needs_lerobot
def test_flow_sde_steps_match_stepnfts_sampler(tiny_folder):
    """Every step of a rollout is N(mean, std²) of sde_step_mean_std at the adapter's velocity."""
    from stepnft.sampling import sde_step_mean_std

    policy = load(tiny_folder)
    obs = policy.processor(raw_obs(256))
    noise_level, steps = 0.7, policy.config.num_inference_steps
    sample = policy.sample(obs, noise_level=noise_level, generator=torch.Generator().manual_seed(1), keep_path=True)
    with torch.no_grad():
        context = policy.encode(obs)
        for k in range(steps):
            t = torch.full((256,), 1.0 - k / steps)
            v = policy.denoise(context, sample.path_x[:, k], t)
            torch.testing.assert_close(v, sample.path_v[:, k])
            mean, std = sde_step_mean_std(sample.path_x[:, k], v, t, torch.full((256,), 1.0 / steps), noise_level)
            z = (sample.path_x[:, k + 1] - mean) / std
            assert abs(float(z.mean())) < 0.1 and abs(float(z.std()) - 1.0) < 0.1, (k, z.mean(), z.std())
    picked = sample.step
    torch.testing.assert_close(sample.x_t, sample.path_x[torch.arange(256), picked])
    torch.testing.assert_close(sample.v_old, sample.path_v[torch.arange(256), picked])


@needs_lerobot
def test_cached_and_joint_velocities_agree(tiny_folder):
    if load(tiny_folder).type != "smolvla":
        with pytest.raises(ValueError, match="prefix_cache=false is SmolVLA's joint pass"):
            load(tiny_folder, prefix_cache=False)
        return
    cached, joint = load(tiny_folder), load(tiny_folder, prefix_cache=False)
    obs = cached.processor(raw_obs(3))
    x, t = torch.randn(3, *cached.chunk_shape), torch.tensor([1.0, 0.5, 0.2])
    with torch.no_grad():
        torch.testing.assert_close(cached.velocity(obs, x, t), joint.velocity(obs, x, t), rtol=1e-4, atol=1e-5)


def rollout_batch(policy, calls: int = 16, group: int = 1):
    """A Batch of Flow-SDE samples from ``policy``, one call per episode, half the episodes
    successful; groups of ``group`` episodes share a reset seed (GRPO's groups)."""
    from stepnft.batch import Batch

    raw = raw_obs(calls)
    sample = policy.sample(policy.processor(raw), noise_level=0.5, generator=torch.Generator().manual_seed(0),
                           keep_path=True)
    steps = sample.all_steps()
    steps["call"] = steps.pop("sample")
    horizon = policy.chunk_shape[0]
    return Batch(episode_success=torch.arange(calls) % 2 == 0, episode_task=torch.zeros(calls, dtype=torch.int64),
                 episode_length=torch.full((calls,), horizon), episode_seed=torch.arange(calls) // group, obs=raw,
                 actions=sample.actions, mask=torch.ones(calls, horizon, dtype=torch.bool), reward=torch.zeros(calls),
                 done=torch.ones(calls, dtype=torch.bool), episode=torch.arange(calls), **steps)


@needs_lerobot
@pytest.mark.parametrize("scope", ["expert", "expert+state"])
def test_a_stepnft_update_changes_only_the_trained_parameters(tiny_folder, scope):
    from stepnft.algos.base import make_optimizer
    from stepnft.algos.stepnft import StepNFTConfig, stepnft_update
    from stepnft.ema import make_ema_copy

    policy = load(tiny_folder, train=scope)
    part = PARTS[policy.type]
    # π0's and π0.5's prefix is the VLM alone (π0's state projection is in the expert's suffix)
    assert policy.prefix_trainable == (scope != "expert" and policy.type == "smolvla")
    ema = make_ema_copy(policy)  # the rollout copy shares the frozen VLM instead of copying it
    assert ema.prefix_modules()[0] is policy.prefix_modules()[0]
    batch = rollout_batch(ema)
    before = {n: p.detach().clone() for n, p in policy.named_parameters()}
    cfg = StepNFTConfig(lr=1e-3, minibatch_size=16, update_epochs=1, max_drift=None, label_balance="none",
                        episode_weighting=False)
    metrics = stepnft_update(policy, make_optimizer(policy.parameters(), cfg), batch, cfg,
                             torch.Generator().manual_seed(0))
    assert metrics["losses/update_steps"] > 0 and metrics["losses/skipped_nonfinite"] == 0
    changed = {n for n, p in policy.named_parameters() if not torch.equal(p, before[n])}
    trained = {n for n, p in policy.named_parameters() if p.requires_grad}
    assert changed and changed <= trained
    assert any("action_out_proj" in n for n in changed) and any(part["expert"] in n for n in changed)
    assert not any(part["vlm"] in n for n in changed)
    assert any("state_proj" in n for n in changed) == part["state_trained"](scope)


def count_prefixes(policy, monkeypatch) -> list[int]:
    """Prefixes the model embeds (images through the vision encoder, into the VLM) per call of its
    ``_embed_prefix``, appended to the returned list."""
    rows, embed = [], policy._embed_prefix

    def counted(obs):
        rows.append(obs["observation.state"].shape[0])
        return embed(obs)

    monkeypatch.setattr(policy, "_embed_prefix", counted)
    return rows


@needs_lerobot
@pytest.mark.parametrize("scope", ["expert", "vlm"])
def test_the_update_encodes_each_calls_prefix_once_with_the_per_step_losses(tiny_folder, scope, monkeypatch):
    """``record_steps: all`` (K = 3 recorded steps per call): π-StepNFT's update takes whole calls
    and encodes each call's prefix once per minibatch, K = 3 times fewer prefixes than the
    per-step path on the same minibatches, with the same losses and gradients (within float
    rounding: 1e-4 relative), into the VLM's layers too when they train (``train: vlm``)."""
    import functools

    from stepnft.algos import stepnft as stepnft_module
    from stepnft.algos.base import step_velocity
    from stepnft.algos.stepnft import StepNFTConfig, stepnft_update

    batch = rollout_batch(load(tiny_folder))  # 16 calls, all 3 steps of each
    cfg = StepNFTConfig(minibatch_size=24, update_epochs=2, max_drift=None, label_balance="none")
    runs = {}
    for share in (True, False):
        policy = load(tiny_folder, train=scope).train()
        vlm = PARTS[policy.type]["vlm"]
        assert policy.shares_prefix_in_update and policy.prefix_trainable == (scope == "vlm")
        prefixes = count_prefixes(policy, monkeypatch)
        if not share:  # the per-step path (one prefix per recorded step) on the same minibatches
            monkeypatch.setattr(stepnft_module, "step_velocity", functools.partial(step_velocity, share_prefix=False))
        # lr 0: the weights stay, and the gradient of the last minibatch stays in .grad to compare
        metrics = stepnft_update(policy, torch.optim.SGD(policy.parameters(), lr=0.0), batch, cfg,
                                 torch.Generator().manual_seed(0))
        grads = {n: p.grad for n, p in policy.named_parameters() if p.grad is not None}
        runs[share] = metrics, prefixes, grads
    (shared, shared_prefixes, shared_grads), (per_step, step_prefixes, step_grads) = runs[True], runs[False]
    assert shared["losses/update_steps"] == 4 and shared["losses/skipped_nonfinite"] == 0
    assert shared_prefixes == [8] * 4 and step_prefixes == [24] * 4  # 8 calls (24 recorded steps) per minibatch
    assert sum(step_prefixes) >= 3 * sum(shared_prefixes)
    for key, value in shared.items():
        assert value == pytest.approx(per_step[key], rel=1e-4, abs=1e-6), key
    assert shared_grads.keys() == step_grads.keys()
    assert any(vlm in n and bool(g.abs().sum() > 0) for n, g in shared_grads.items()) == (scope == "vlm")
    for name, grad in shared_grads.items():
        torch.testing.assert_close(grad, step_grads[name], rtol=1e-4, atol=1e-6, msg=name)


@needs_lerobot
def test_a_grpo_update_shares_each_calls_prefix_and_trains_the_expert(tiny_folder, monkeypatch):
    """GRPO's clipped surrogate (PPO's too: ``policy_gradient_update``) on whole calls: one
    prefix per call, and only the trained parameters move."""
    from stepnft.algos.base import make_optimizer
    from stepnft.algos.grpo import GRPOConfig
    from stepnft.algos.likelihood import policy_gradient_update

    policy = load(tiny_folder)
    batch = rollout_batch(policy)
    prefixes = count_prefixes(policy, monkeypatch)
    before = {n: p.detach().clone() for n, p in policy.named_parameters()}
    cfg = GRPOConfig(lr=1e-3, minibatch_size=24, update_epochs=1, group_size=2)
    metrics = policy_gradient_update(policy, make_optimizer(policy.parameters(), cfg), batch,
                                     torch.where(torch.arange(16) % 2 == 0, 1.0, -1.0), cfg,
                                     torch.Generator().manual_seed(0))
    assert metrics["losses/update_steps"] == 2 and prefixes == [8, 8]  # 8 calls of 3 recorded steps each
    changed = {n for n, p in policy.named_parameters() if not torch.equal(p, before[n])}
    assert changed and changed <= {n for n, p in policy.named_parameters() if p.requires_grad}


@needs_lerobot
def test_every_variant_of_stepnft_compare_updates_each_model(tiny_folder):
    """Every algorithm and ablation `stepnft compare` knows (π-StepNFT's ablations, PPO, GRPO and
    theirs) samples a batch as its own rollout spec asks (noise, stochastic steps, recorded steps,
    mean correction, groups) and takes one finite update on each VLA."""
    from stepnft.algos.base import make_algorithm
    from stepnft.algos.stepnft import StepNFTConfig
    from stepnft.algos.variants import VARIANTS, variant_config
    from stepnft.batch import Batch

    policy = load(tiny_folder)
    base = StepNFTConfig(lr=1e-3, minibatch_size=24, update_epochs=1)
    calls, horizon = 8, policy.chunk_shape[0]
    raw = raw_obs(calls)
    for name in VARIANTS:
        learner = make_algorithm(variant_config(name, base), policy, iterations=1,
                                 generator=torch.Generator().manual_seed(0))
        spec = learner.rollout
        sample = learner.acting_policy().sample(
            policy.processor(raw), noise_level=spec.noise_level, generator=torch.Generator().manual_seed(1),
            stochastic_steps=spec.stochastic_steps, keep_path=spec.record_steps == "all",
            mean_correction=spec.mean_correction)
        success = torch.arange(calls) % 2 == 0
        batch = Batch(episode_success=success, episode_task=torch.zeros(calls, dtype=torch.int64),
                      episode_length=torch.full((calls,), horizon),
                      episode_seed=torch.arange(calls) // max(spec.group_size, 1), obs=raw, actions=sample.actions,
                      mask=torch.ones(calls, horizon, dtype=torch.bool), reward=success.float() * torch.rand(calls),
                      done=torch.ones(calls, dtype=torch.bool), episode=torch.arange(calls),
                      **sample.recorded_steps(every_step=spec.record_steps == "all"))
        metrics = learner.update(batch)
        assert metrics["losses/skipped_nonfinite"] == 0, name
        assert all(np.isfinite(v) for k, v in metrics.items() if k.startswith("losses/") and isinstance(v, float)), name


@needs_lerobot
def test_select_context_gives_each_step_its_calls_prefix(tiny_folder):
    """Rows of the KV cache and masks (without the cache: of the observations): denoising against
    a selected prefix is denoising each call against its own."""
    cached = load(tiny_folder)
    for policy in (cached, load(tiny_folder, prefix_cache=False)) if cached.type == "smolvla" else (cached,):
        obs = policy.processor(raw_obs(3))
        rows = torch.tensor([2, 0, 0, 1, 2])
        x, t = torch.randn(5, *policy.chunk_shape), torch.tensor([1.0, 0.6, 0.3, 1.0, 0.3])
        with torch.no_grad():
            shared = policy(obs, x, t, context_rows=rows)
            own = policy.velocity({k: v[rows] for k, v in obs.items()}, x, t)
        torch.testing.assert_close(shared, own, rtol=1e-5, atol=1e-6)


@needs_lerobot
def test_a_checkpoint_keeps_only_the_ema_copys_own_tensors_and_resumes_it_exactly(tiny_folder, tmp_path):
    """``train: expert``: the EMA copy shares the frozen VLM and state projection with the
    policy, so the checkpoint stores them once (in ``policy/``); resume rebuilds the EMA copy
    exactly; a checkpoint holding the whole EMA state (as before) resumes too."""
    from stepnft.algos.stepnft import StepNFT, StepNFTConfig
    from stepnft.checkpoint import load_checkpoint, save_checkpoint

    policy = load(tiny_folder)
    cfg = StepNFTConfig(lr=1e-3, minibatch_size=24, update_epochs=1)
    algo = StepNFT(policy, cfg, iterations=4, generator=torch.Generator().manual_seed(0))
    algo.update(rollout_batch(algo.ema))
    algo.end_iteration(0)
    save_checkpoint(tmp_path, 1, policy, {"algorithm": algo.state_dict()})
    ckpt = load_checkpoint(tmp_path)
    saved = ckpt["state"]["algorithm"]["ema"]
    frozen = {n for n, p in policy.named_parameters() if not p.requires_grad}
    trained = {n for n, p in policy.named_parameters() if p.requires_grad}
    assert frozen and not (saved.keys() & frozen) and trained <= saved.keys()
    assert not any(PARTS[policy.type]["vlm"] in k for k in saved)
    assert any("state_proj" in k for k in saved) == PARTS[policy.type]["state_trained"]("expert")
    whole = algo.ema.state_dict()
    size = sum(v.numel() * v.element_size() for v in saved.values())
    assert size < 0.6 * sum(v.numel() * v.element_size() for v in whole.values())  # 450 M: 22 % (trained share)

    def resumed(state):
        other = StepNFT(ckpt["policy"], cfg, iterations=4, generator=torch.Generator())
        other.load_state_dict(ckpt["state"]["algorithm"] | state)
        assert other.ema.prefix_modules()[0] is other.policy.prefix_modules()[0]
        return other.ema.state_dict()

    for state in ({}, {"ema": whole}):  # this checkpoint, and one holding the whole EMA state
        again = resumed(state)
        assert again.keys() == whole.keys() and all(torch.equal(again[k], whole[k]) for k in whole)


@needs_lerobot
def test_value_features_pool_the_prefix_hidden_states_and_add_the_state(tiny_folder):
    """What PPO's value head reads: the VLM's last-layer hidden states of the prefix averaged over
    its valid tokens (padding excluded), then the normalised state; from the pass that fills the
    cache; in chunks of VALUE_CHUNK calls."""
    from stepnft.policies.lerobot.adapter import VALUE_CHUNK

    policy = load(tiny_folder)
    policy.processor.bind_instructions(["reach", "put every action of the chunk on the target"])
    raw = raw_obs(VALUE_CHUNK + 5)
    obs = policy.processor(raw | {"task": torch.arange(VALUE_CHUNK + 5) % 2})  # the short one is padded
    model = policy.lerobot.model
    with torch.no_grad():
        features = policy.value_features(obs)
        embs, pad_masks, att_masks = policy._embed_prefix(obs)
        if policy.type == "smolvla":
            from lerobot.policies.smolvla.modeling_smolvla import make_att_2d_masks

            (hidden, _), _ = model.vlm_with_expert.forward(
                attention_mask=make_att_2d_masks(pad_masks, att_masks), position_ids=torch.cumsum(pad_masks, dim=1) - 1,
                past_key_values=None, inputs_embeds=[embs, None], use_cache=True,
                **({"fill_kv_cache": True} if policy._dict_cache else {}))  # LeRobot 0.4's dict cache
        else:  # π0 / π0.5: LeRobot's prefix pass of sample_actions, the VLM's Gemma alone
            from lerobot.policies.common.vla_utils import make_att_2d_masks, prepare_attention_masks_4d

            hidden = policy.language_model(
                inputs_embeds=embs, attention_mask=prepare_attention_masks_4d(make_att_2d_masks(pad_masks, att_masks)),
                position_ids=torch.cumsum(pad_masks, dim=1) - 1, use_cache=True).last_hidden_state
        context = policy.encode(obs)
    width = vlm_width(policy)
    assert features.shape == (VALUE_CHUNK + 5, width + 2)
    assert bool((~pad_masks).any())  # there is padding to leave out
    valid = pad_masks[..., None].float()
    pooled = (hidden * valid).sum(1) / valid.sum(1)
    torch.testing.assert_close(features[:, :width], pooled)
    assert not torch.allclose(pooled, hidden.mean(1))
    torch.testing.assert_close(features[:, width:], obs["observation.state"])
    torch.testing.assert_close(context.pooled, pooled)  # the encode's pass carries them too
    # ``train: expert`` freezes the prefix: the features are constants; with ``vlm`` a loss on
    # them reaches the VLM's language layers (a value head sharing the encoder trains them).
    assert not policy.value_features(policy.processor(raw_obs(2))).requires_grad
    vlm = load(tiny_folder, train="vlm")
    vlm.value_features(vlm.processor(raw_obs(2))).square().sum().backward()
    reached = {n for n, p in vlm.named_parameters() if p.grad is not None and bool(p.grad.abs().sum() > 0)}
    part = PARTS[policy.type]
    # The vision encoder trains as LeRobot's own flag says (SmolVLA's default freezes it, π0's does not).
    vision_trains = not vlm.lerobot.config.freeze_vision_encoder
    assert any(part["lm"] in n for n in reached) and any(part["vision"] in n for n in reached) == vision_trains


@needs_lerobot
@pytest.mark.parametrize("algo, scope, shared", [("ppo", "expert", False), ("ppo", "vlm", True),
                                                 ("grpo", "expert+state", False)])
def test_ppo_and_grpo_updates_change_only_the_trained_parameters(tiny_folder, algo, scope, shared):
    """PPO (its value head on the pooled prefix and the state; detached, or sharing a trained
    VLM) and GRPO update each model through the same velocity calls as π-StepNFT."""
    from stepnft.algos.base import make_algorithm
    from stepnft.algos.grpo import GRPOConfig
    from stepnft.algos.ppo import PPOConfig

    policy = load(tiny_folder, train=scope)
    part = PARTS[policy.type]
    batch = rollout_batch(policy, group=4)
    before = {n: p.detach().clone() for n, p in policy.named_parameters()}
    cfg = (PPOConfig(lr=1e-3, minibatch_size=24, update_epochs=1, critic_shares_encoder=shared) if algo == "ppo"
           else GRPOConfig(lr=1e-3, minibatch_size=24, update_epochs=1))
    learner = make_algorithm(cfg, policy, iterations=1, generator=torch.Generator().manual_seed(0))
    metrics = learner.update(batch)
    assert metrics["losses/update_steps"] == 2 and metrics["losses/skipped_nonfinite"] == 0  # 16 calls, 8 a step
    assert np.isfinite(metrics["losses/policy_loss"])
    if algo == "ppo":
        assert learner.critic.net[0].in_features == vlm_width(policy) + 2 and np.isfinite(metrics["losses/value_loss"])
        assert (learner.critic_optimizer is None) == shared
    changed = {n for n, p in policy.named_parameters() if not torch.equal(p, before[n])}
    trained = {n for n, p in policy.named_parameters() if p.requires_grad}
    assert changed and changed <= trained and any(part["expert"] in n for n in changed)
    vision_trains = scope == "vlm" and not policy.lerobot.config.freeze_vision_encoder  # LeRobot's own flag
    assert any(part["vision"] in n for n in changed) == vision_trains
    assert any(part["vlm"] in n for n in changed) == (scope == "vlm")
    assert any("state_proj" in n for n in changed) == part["state_trained"](scope)


@needs_lerobot
def test_save_load_round_trip_gives_the_same_actions(tiny_folder, tmp_path):
    from stepnft.algos.sft import SFTConfig, sft_train
    from stepnft.policies.base import load_policy

    policy = load(tiny_folder)
    raw = raw_obs(64, seed=5)
    actions = torch.rand(64, 2, 2) * 0.5
    policy.processor.fit(raw["state"], actions)  # statistics travel in LeRobot's pipelines
    sft_train(policy, {"obs": raw, "actions": actions, "mask": torch.ones(64, 2, dtype=torch.bool)},
              SFTConfig(steps=3, batch_size=16), torch.Generator().manual_seed(0))
    policy.save_pretrained(tmp_path / "saved")
    # LeRobot's own files: a LeRobot user loads lerobot/ with SmolVLAPolicy / PI0Policy / PI05Policy.from_pretrained
    assert {"config.json", "model.safetensors", "policy_preprocessor.json",
            "policy_postprocessor.json"} <= {p.name for p in (tmp_path / "saved" / "lerobot").iterdir()}
    loaded = load_policy(tmp_path / "saved")
    loaded.processor.bind_instructions(policy.processor.instructions)
    assert loaded.config == policy.config
    for a, b in ((policy, loaded),):
        x = a.sample(a.processor(raw), generator=torch.Generator().manual_seed(2)).actions
        y = b.sample(b.processor(raw), generator=torch.Generator().manual_seed(2)).actions
        torch.testing.assert_close(x, y, rtol=0, atol=0)
        torch.testing.assert_close(a.env_actions(x), b.env_actions(y), rtol=0, atol=0)
    # the robot's actions are LeRobot's un-normalised ones, and model_actions inverts them
    stats = policy.processor.stats["action"]
    if policy.type == "pi05":  # π0.5 normalises by quantiles: [q01, q99] -> [-1, 1]
        low, high = torch.tensor(stats["q01"]), torch.tensor(stats["q99"])
        expected = (x[..., :2] + 1) / 2 * (high - low) + low
    else:
        expected = x[..., :2] * torch.tensor(stats["std"]) + torch.tensor(stats["mean"])
    torch.testing.assert_close(policy.env_actions(x), expected)
    torch.testing.assert_close(policy.model_actions(policy.env_actions(x)), x, rtol=1e-5, atol=1e-5)


@needs_lerobot
def test_lerobots_own_from_pretrained_loads_a_stepnft_folder_and_selects_the_same_actions(tiny_folder, tmp_path):
    """What a LeRobot user does with a policy stepnft fine-tuned: ``<Model>Policy.from_pretrained``
    on its ``lerobot/`` folder and LeRobot's own pre-processor, post-processor and
    ``predict_action_chunk``: the same robot actions as stepnft's ODE sampler on the same noise."""
    import importlib

    from lerobot.processor import PolicyProcessorPipeline
    from stepnft.algos.sft import SFTConfig, sft_train
    from stepnft.policies.lerobot.processor import (batch_to_transition, policy_action_to_transition,
                                                    transition_to_batch, transition_to_policy_action)

    policy = load(tiny_folder)
    raw = raw_obs(64, seed=5)
    actions = torch.rand(64, 2, 2) * 0.5
    policy.processor.fit(raw["state"], actions)
    sft_train(policy, {"obs": raw, "actions": actions, "mask": torch.ones(64, 2, dtype=torch.bool)},
              SFTConfig(steps=3, batch_size=16), torch.Generator().manual_seed(0))
    policy.save_pretrained(tmp_path / "saved")
    model = policy.type
    policy_class = getattr(importlib.import_module(f"lerobot.policies.{model}.modeling_{model}"),
                           {"smolvla": "SmolVLAPolicy", "pi0": "PI0Policy", "pi05": "PI05Policy"}[model])
    folder = tmp_path / "saved" / "lerobot"
    theirs = policy_class.from_pretrained(folder).eval()
    pre = PolicyProcessorPipeline.from_pretrained(folder, config_filename="policy_preprocessor.json",
                                                  to_transition=batch_to_transition, to_output=transition_to_batch)
    post = PolicyProcessorPipeline.from_pretrained(folder, config_filename="policy_postprocessor.json",
                                                   to_transition=policy_action_to_transition,
                                                   to_output=transition_to_policy_action)
    batch = policy.processor.lerobot_batch(raw_obs(4, seed=1))  # the raw LeRobot batch: state, images, task
    noise = torch.randn((4, *policy.chunk_shape), generator=torch.Generator().manual_seed(7))
    with torch.no_grad():
        chunk = theirs.predict_action_chunk(pre(batch), noise=noise)
        ours = policy.sample(policy.processor(raw_obs(4, seed=1)), noise_level=0.0,
                             generator=torch.Generator().manual_seed(7))
    torch.testing.assert_close(policy.env_actions(ours.actions), post(chunk), rtol=1e-5, atol=1e-5)


@needs_lerobot
def test_a_plain_lerobot_folder_loads_as_is(tiny_folder, tmp_path):
    """What LeRobot itself saves (config.json with its "type", weights, pipelines) is a policy."""
    from stepnft.policies.base import load_policy

    policy = load(tiny_folder)
    plain = tmp_path / "plain"
    policy.lerobot.save_pretrained(plain)
    policy.processor.save(plain)
    loaded = load_policy(plain)
    assert loaded.type == policy.type and loaded.config.lerobot == "." and loaded.config.n_exec == 2
    loaded.processor.bind_instructions(policy.processor.instructions)
    raw = raw_obs(3)
    x = policy.sample(policy.processor(raw), generator=torch.Generator().manual_seed(0)).actions
    y = loaded.sample(loaded.processor(raw), generator=torch.Generator().manual_seed(0)).actions
    torch.testing.assert_close(x, y)


@needs_lerobot
def test_processor_errors_are_one_line(tiny_folder):
    policy = load(tiny_folder)
    raw = raw_obs(2)
    with pytest.raises(ValueError, match="sees camera images"):
        policy.processor({k: v for k, v in raw.items() if k != "image"})
    with pytest.raises(ValueError, match="takes 2-d states, the env gives 3-d"):
        policy.processor(raw | {"state": torch.zeros(2, 3)})


@needs_lerobot
def test_pi0_and_pi05_say_what_is_missing():
    from stepnft.policies.lerobot.configuration import LeRobotPolicyConfig
    from stepnft.policies.lerobot.pi0 import PI0Adapter, PI05Adapter, PiUnavailable, needs_patched_transformers

    if not needs_patched_transformers():
        pytest.skip("π0 builds here (LeRobot 0.6, or 0.4 with its patched transformers)")
    from lerobot.policies.pi0.configuration_pi0 import PI0Config
    from lerobot.policies.pi05.configuration_pi05 import PI05Config

    for adapter, config in ((PI0Adapter, PI0Config), (PI05Adapter, PI05Config)):
        with pytest.raises(PiUnavailable, match="patched transformers") as err:
            adapter.build(LeRobotPolicyConfig(), config(device="cpu"), None, None)
        assert "\n" not in str(err.value)


@needs_lerobot
@pytest.mark.slow
def test_demos_sft_and_train_from_the_cli_and_resume(tiny_folder, tmp_path, monkeypatch, capsys):
    """The LeRobot user's path on the image bandit: `stepnft demos` with cameras, `stepnft sft
    --init <new VLA>` on them, `stepnft train --init RUN/policy`, checkpoints, resume, eval."""
    from stepnft.cli import main
    from stepnft.envs import SIMULATORS, SimulatorInfo
    from stepnft.policies.base import load_policy

    def run(*argv):
        assert main([str(a) for a in argv]) == 0, capsys.readouterr().err

    monkeypatch.setitem(SIMULATORS, "bandit-image", SimulatorInfo(f"{__name__}:ImageBandit", 64, ("bandit",)))
    env = ["--env.name", "bandit-image", "--env.tasks", "bandit", "--env.cameras", "synthetic", "--env.image-size", IMAGE,
           "--env.max-episode-steps", "2"]
    demos = ["--demos.path", tmp_path / "demos", "--demos.episodes", "16"]
    run("demos", *env, *demos)
    assert json.loads((tmp_path / "demos" / "manifest.json").read_text())["generator"]["cameras"] == ["synthetic"]
    run("sft", "--init", tiny_folder, "--run-dir", tmp_path / "sft", *env, *demos, "--sft.steps", "3",
        "--sft.batch-size", "8", "--env.envs-per-task", "8", "--eval.episodes", "0")
    assert json.loads((tmp_path / "sft" / "summary.json").read_text()) == {"sft": None}  # `train` evaluates it
    sft = load_policy(tmp_path / "sft" / "policy")
    model = json.loads((tiny_folder / "config.json").read_text())["type"]
    assert sft.type == model and sft.config.cameras == ["synthetic"] and not sft.processor.needs_fit
    assert load_policy(tiny_folder).processor.needs_fit  # the --init folder itself is left as it was

    argv = ["train", "--init", tmp_path / "sft" / "policy", "--run-dir", tmp_path / "rl", "--iterations", "2",
            "--episodes-per-iteration", "8", "--eval.every", "1", "--checkpoint-every", "1", "--algo.minibatch-size", "8",
            *env, "--env.envs-per-task", "8", "--eval.episodes", "8", "--eval.during-episodes", "8", "--eval.seed", "100"]
    run(*argv)
    summary = json.loads((tmp_path / "rl" / "summary.json").read_text())
    assert summary["iterations"] == 2 and summary["env_steps"] > 0
    records = [json.loads(line) for line in (tmp_path / "rl" / "metrics.jsonl").read_text().splitlines()]
    assert any(r.get("losses/update_steps", 0) > 0 for r in records)
    final = load_policy(tmp_path / "rl" / "policy")
    assert final.type == model and (tmp_path / "rl" / "checkpoints" / "LATEST").is_file()
    run("train", "--resume", tmp_path / "rl")  # finished: resumes to the same end
    # The env's cameras follow the policy's in `stepnft eval` (its suites bind instructions too).
    run("eval", "--policy", tmp_path / "rl" / "policy", "--env.name", "bandit-image", "--env.tasks", "bandit",
        "--env.image-size", IMAGE, "--env.max-episode-steps", "2", "--eval.episodes", "4")

    # Cameras other than the policy's: one line before anything is written.
    capsys.readouterr()
    assert main([str(a) for a in argv[:3]] + ["--run-dir", str(tmp_path / "nocam"), "--env.name", "bandit-image",
                                               "--env.tasks", "bandit", "--env.max-episode-steps", "2"]) == 2
    assert "sees cameras ['synthetic'], env.cameras is []" in capsys.readouterr().err
    assert not (tmp_path / "nocam").exists()


@needs_lerobot
@pytest.mark.slow
@pytest.mark.parametrize("model", MODELS)
def test_compare_stepnft_ppo_and_grpo_with_a_vla_on_a_metaworld_camera_task(tmp_path, monkeypatch, model):
    """`stepnft compare --algos stepnft,ppo,grpo` with a new tiny VLA of each model on reach-v3 seen through
    MetaWorld's corner camera, at a tiny budget: the SmolVLA (the base config's ``init``) is the
    SFT start, each algorithm trains the SFT policy through the CLI (PPO's value head on the
    pooled prefix and the state), the report has every row. A functional check, not a result."""
    from stepnft.algos.sft import SFTConfig
    from stepnft.algos.stepnft import StepNFTConfig
    from stepnft.cli import main
    from stepnft.config import DemoConfig, EnvConfig, EvalConfig, TrainConfig, save_config
    from stepnft.policies.base import load_policy
    from stepnft.policies.lerobot.tiny import NewVLA, new_vla
    from stepnft.runs import read_metrics

    skip_without(model)
    monkeypatch.setenv("MUJOCO_GL", "egl")
    vla = tmp_path / f"tiny_{model}"
    new_vla(NewVLA(out=str(vla), model=model, state_dim=39, action_dim=4, chunk_size=4, n_exec=4, num_steps=2,
                   cameras=["corner"], image_size=32, train="expert+state"))
    base = TrainConfig(
        init=str(vla), iterations=2, episodes_per_iteration=4, checkpoint_every=1,
        env=EnvConfig(tasks=["reach-v3"], cameras=["corner"], image_size=32, max_episode_steps=60, envs_per_task=4),
        demos=DemoConfig(episodes=2), sft=SFTConfig(steps=2, batch_size=8),
        eval=EvalConfig(episodes=2, every=0), algo=StepNFTConfig(minibatch_size=16))
    save_config(base, tmp_path / "base.yaml")
    out = tmp_path / "compare"
    code = main(["compare", "--config", str(tmp_path / "base.yaml"), "--algos", "stepnft,ppo,grpo", "--seeds", "0",
                 "--env-steps", "300", "--jobs", "1", "--out", str(out)])
    logs = {p.name: p.read_text()[-2000:] for p in (out / "logs").glob("*.log")}
    assert code == 0, logs
    assert load_policy(out / "sft" / "seed0" / "policy").type == model
    table = (out / "comparison.md").read_text()
    for algo in ("stepnft", "ppo", "grpo"):
        run = out / "runs" / algo / "seed0"
        assert f"| {algo} |" in table
        assert json.loads((run / "summary.json").read_text())["env_steps"] >= 300
        assert load_policy(run / "policy").type == model
        records = read_metrics(run / "metrics.jsonl")
        # GRPO's groups of an untrained policy may all fail alike: its minibatches are then skipped
        # (its steps on a SmolVLA: test_ppo_and_grpo_updates_change_only_the_trained_parameters).
        counted = ("losses/update_steps", "losses/skipped_empty") if algo == "grpo" else ("losses/update_steps",)
        assert any(sum(r.get(k, 0) for k in counted) > 0 for r in records), algo
        if algo == "ppo":
            assert all(np.isfinite(r["losses/value_loss"]) for r in records if "losses/value_loss" in r)
            assert any("losses/value_loss" in r for r in records)
