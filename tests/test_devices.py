"""``--device``: the policy computes on it, everything else (simulators, processors, batches,
checkpoints, random generators) stays on the CPU. The CPU-only checks use the ``meta`` device as
a stand-in for a GPU (tensors with shapes and no data); the CUDA test runs where a GPU is."""

import copy
import dataclasses

import pytest
import torch

from stepnft.algos.base import make_algorithm
from stepnft.rollout.plan import RolloutSpec
from stepnft.algos.ppo import PPOConfig
from stepnft.algos.sft import SFTConfig, sft_stage
from stepnft.algos.stepnft import StepNFTConfig
from stepnft.batch import Batch
from stepnft.checkpoint import load_checkpoint, save_checkpoint
from stepnft.cli import main
from stepnft.config import DemoConfig, EnvConfig, EvalCommand, TrainConfig
from stepnft.data.demos import generate_demos
from stepnft.devices import resolve_device, to_device
from stepnft.envs import get_simulator, make_vec_env
from stepnft.envs.bandit import ACTION_DIM, CONTEXT_DIM, HORIZON
from stepnft.policies.flow import FlowPolicy, FlowPolicyConfig
from stepnft.rollout.collector import Collector
from stepnft.sampling import ChunkSample

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")

POLICY = FlowPolicyConfig(state_dim=CONTEXT_DIM, lang_dim=0, action_dim=ACTION_DIM, horizon=HORIZON, n_exec=HORIZON,
                          hidden_dim=64)


def tiny_batch(n=4) -> Batch:
    chunk = torch.randn(n, HORIZON, ACTION_DIM)
    return Batch(episode_success=torch.ones(n, dtype=torch.bool), episode_task=torch.zeros(n, dtype=torch.int64),
                 episode_length=torch.full((n,), 2), episode_seed=torch.full((n,), -1),
                 obs={"state": torch.randn(n, CONTEXT_DIM), "task": torch.zeros(n, dtype=torch.int64)},
                 actions=chunk, mask=torch.ones(n, HORIZON, dtype=torch.bool), reward=torch.zeros(n),
                 done=torch.ones(n, dtype=torch.bool), episode=torch.arange(n), call=torch.arange(n), x_t=chunk,
                 x_next=chunk, v_old=chunk, t=torch.ones(n), dt=torch.ones(n))


def tensors_of(batch: Batch) -> dict[str, torch.Tensor]:
    out = {f.name: getattr(batch, f.name) for f in dataclasses.fields(batch) if f.name != "obs"}
    return out | {f"obs.{k}": v for k, v in batch.obs.items()}


def test_to_device_moves_every_tensor_through_the_structure():
    batch = tiny_batch()
    moved = to_device(batch, "meta")
    assert isinstance(moved, Batch) and moved.num_steps == batch.num_steps  # re-validated
    assert all(v.device.type == "meta" for v in tensors_of(moved).values())
    assert all(v.device.type == "cpu" for v in tensors_of(batch).values())  # the original is kept
    # Already there: the very same tensors, no copies (the CPU path costs nothing).
    assert all(a is b for a, b in zip(tensors_of(to_device(batch, "cpu")).values(), tensors_of(batch).values()))
    sample = ChunkSample(*(torch.zeros(2, 1) for _ in range(7)))
    moved = to_device(sample, "meta")
    assert moved.actions.device.type == "meta" and moved.path_x is None
    obs, x, w, n = to_device(({"state": torch.zeros(1)}, torch.zeros(1), None, 3), "meta")
    assert obs["state"].is_meta and x.is_meta and w is None and n == 3


def test_the_processor_stays_on_the_cpu_and_the_noise_comes_from_the_cpu_generators():
    """A policy moved to another device gets its inputs processed on the CPU then moved, and
    samples with noise drawn from the CPU generators: the same draws as on the CPU."""
    torch.manual_seed(0)
    policy = FlowPolicy(POLICY)
    policy.processor.fit(torch.randn(16, CONTEXT_DIM))
    raw = {"state": torch.randn(3, CONTEXT_DIM), "task": torch.zeros(3, dtype=torch.int64)}
    on_cpu = [torch.Generator().manual_seed(i) for i in range(3)]
    policy.sample(policy.prepare(raw), noise_level=0.3, generator=on_cpu, keep_path=True)

    elsewhere = copy.deepcopy(policy).to("meta")
    assert elsewhere.device.type == "meta" and policy.device.type == "cpu"
    assert elsewhere.processor.state_mean.device.type == "cpu"
    inputs = elsewhere.prepare(raw)
    assert inputs["state"].is_meta
    generators = [torch.Generator().manual_seed(i) for i in range(3)]
    sample = elsewhere.sample(inputs, noise_level=0.3, generator=generators, keep_path=True)
    assert sample.actions.is_meta and sample.path_x.is_meta
    for a, b in zip(on_cpu, generators):  # every draw was taken from the CPU generators
        assert torch.equal(a.get_state(), b.get_state())


def test_device_setting_is_checked():
    assert TrainConfig().device == "cpu" and EvalCommand().device == "cpu"
    assert TrainConfig(device="cuda:1").device == "cuda:1"
    for bad in ("gpu", "cuda:", "CUDA", "mps"):
        with pytest.raises(ValueError, match="device"):
            TrainConfig(device=bad)
        with pytest.raises(ValueError, match="device"):
            EvalCommand(device=bad)
    assert resolve_device("cpu") == torch.device("cpu")


@pytest.mark.parametrize("command", ["train", "sft", "eval"])
def test_cuda_without_cuda_is_one_line_exit_2_and_creates_nothing(command, capsys, tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    where = ["--run-dir", str(tmp_path / "run")] if command != "eval" else ["--out", str(tmp_path / "run" / "r.json")]
    assert main([command, "--device", "cuda", *where]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "CUDA is not available here" in err and "--device cpu" in err, err
    assert not (tmp_path / "run").exists()
    assert main([command, "--device", "gpu", *where]) == 2
    assert "--device must be cpu, cuda or cuda:N, got 'gpu'" in capsys.readouterr().err


# --- on a GPU -----------------------------------------------------------------------------------
def close(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor], atol: float = 1e-4, rtol: float = 1e-3) -> None:
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k].cpu(), b[k].cpu(), rtol=rtol, atol=atol, msg=lambda m: f"{k}: {m}")


TRAINED = {"atol": 1e-3, "rtol": 1e-2}
"""Weights after Adam steps: a gradient near 0 is normalised to a step of about ``lr`` whatever
its rounding, so CPU and GPU weights may differ by a few ``lr`` there."""


def sft(device: str, root) -> FlowPolicy:
    """A bandit SFT policy trained on ``device`` (the demonstrations generated on the first call)."""
    demos = DemoConfig(path=str(root / "demos"), episodes=200, successful_only=False)
    if not (root / "demos").exists():
        generate_demos(["bandit"], 200, demos.path, simulator=get_simulator("bandit"), successful_only=False,
                       max_episode_steps=HORIZON, progress=False)
    torch.manual_seed(0)  # the same initial weights on every device
    env = EnvConfig(name="bandit", tasks=["bandit"], max_episode_steps=HORIZON)
    return sft_stage(env, demos, POLICY, SFTConfig(steps=100, batch_size=64, lr=1e-3), seed=0, log=lambda s: None,
                     device=device)


def rollout(policy, episodes=64) -> Batch:
    env = EnvConfig(name="bandit", tasks=["bandit"], envs_per_task=episodes, max_episode_steps=HORIZON)
    collector = Collector(make_vec_env(env, HORIZON, seed=0), seed=0)
    try:
        return collector.collect(policy, episodes, RolloutSpec(0.3, record_steps="all"))
    finally:
        collector.close()


@cuda
def test_sft_rollout_update_and_checkpoint_on_cuda_match_the_cpu(tmp_path):
    # SFT: the same minibatches and noise (CPU generators) -> the same weights up to rounding.
    on_cpu, on_gpu = sft("cpu", tmp_path), sft("cuda", tmp_path)
    assert on_gpu.device.type == "cuda" and on_cpu.device.type == "cpu"
    close(on_cpu.state_dict(), on_gpu.state_dict(), **TRAINED)

    # Rollout from the same weights: the batch comes back on the CPU with the same chunks.
    on_gpu = copy.deepcopy(on_cpu).to("cuda")
    batch, gpu_batch = rollout(on_cpu), rollout(on_gpu)
    assert all(v.device.type == "cpu" for v in tensors_of(gpu_batch).values())
    floats = [k for k, v in tensors_of(batch).items() if v.is_floating_point() and k != "reward"]
    close({k: tensors_of(batch)[k] for k in floats}, {k: tensors_of(gpu_batch)[k] for k in floats})
    assert (batch.episode_success == gpu_batch.episode_success).float().mean() >= 0.95

    # One update of each kind on the same CPU batch: the same weights, EMA, critic and metrics.
    for cfg in (StepNFTConfig(noise_level=0.3, minibatch_size=64), PPOConfig(noise_level=0.3, minibatch_size=32)):
        algos = []
        for policy in (copy.deepcopy(on_cpu), copy.deepcopy(on_cpu).to("cuda")):
            torch.manual_seed(1)  # PPO's critic is built on the first batch
            algo = make_algorithm(cfg, policy, 3, torch.Generator().manual_seed(0))
            metrics = algo.update(batch) | algo.end_iteration(0)
            algos.append((algo, metrics))
        (cpu_algo, cpu_metrics), (gpu_algo, gpu_metrics) = algos
        assert gpu_metrics.keys() == cpu_metrics.keys() and gpu_metrics["losses/update_steps"] > 0
        for k, v in cpu_metrics.items():
            assert gpu_metrics[k] == pytest.approx(v, rel=1e-2, abs=1e-3, nan_ok=True), k
        close(cpu_algo.policy.state_dict(), gpu_algo.policy.state_dict(), **TRAINED)
        state = gpu_algo.state_dict()
        if cfg.name == "stepnft":
            assert gpu_algo.ema.device.type == "cuda"
            close(cpu_algo.ema.state_dict(), state["ema"], **TRAINED)
        else:
            assert next(gpu_algo.critic.parameters()).is_cuda
            close(cpu_algo.critic.state_dict(), state["critic"], **TRAINED)
        exp_avg = next(iter(gpu_algo.optimizer.state.values()))["exp_avg"]
        assert exp_avg.is_cuda

        # Checkpoints hold CPU tensors; a resumed CUDA algorithm gets its state back on the GPU.
        run = tmp_path / cfg.name
        save_checkpoint(run, 1, gpu_algo.policy, {"algorithm": state})
        ckpt = load_checkpoint(run)
        assert ckpt["policy"].device.type == "cpu"
        resumed = make_algorithm(cfg, ckpt["policy"].to("cuda"), 3, torch.Generator())
        resumed.load_state_dict(ckpt["state"]["algorithm"])
        close(gpu_algo.policy.state_dict(), resumed.policy.state_dict(), atol=0)
        assert next(iter(resumed.optimizer.state.values()))["exp_avg"].is_cuda
        if cfg.name == "stepnft":
            assert resumed.ema.device.type == "cuda"
            close(state["ema"], resumed.ema.state_dict(), atol=0)


@cuda
def test_a_bandit_run_trains_and_resumes_on_cuda(tmp_path):
    from stepnft.demo_bandit import bandit_config
    from stepnft.train import train

    cfg = bandit_config(run_dir=str(tmp_path / "run"), device="cuda", iterations=2, episodes_per_iteration=64,
                        checkpoint_every=1)
    cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, envs_per_task=64),
                              demos=dataclasses.replace(cfg.demos, path=str(tmp_path / "demos"), episodes=200),
                              sft=dataclasses.replace(cfg.sft, steps=50),
                              eval=dataclasses.replace(cfg.eval, episodes=64, during_episodes=64))
    summary = train(cfg, log=lambda s: None)
    assert summary["iterations"] == 2 and 0 <= summary["average"]["after"] <= 1
    assert load_checkpoint(cfg.run_dir)["policy"].device.type == "cpu"
    assert main(["train", "--resume", cfg.run_dir, "--device", "cpu"]) == 0  # a CUDA run may resume on the CPU


def test_bf16_note_names_the_cap_only_where_the_cpu_has_bf16_units_and_the_cap_is_on(monkeypatch):
    from stepnft.devices import bf16_capped_note

    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    note = bf16_capped_note({"avx2", "avx512f", "avx512_bf16"})
    assert note is not None and "ONEDNN_MAX_CPU_ISA=ALL" in note and "\n" not in note
    assert bf16_capped_note({"avx2", "amx_bf16"}) is not None
    assert bf16_capped_note({"avx2", "avx512f"}) is None  # no bf16 units: the cap costs nothing
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "ALL")
    assert bf16_capped_note({"avx512_bf16"}) is None


def test_set_precision_bf16_warns_once_per_call_under_the_cap_on_a_bf16_cpu(monkeypatch):
    import warnings

    import stepnft.policies.base as base

    monkeypatch.setattr(base, "bf16_capped_note", lambda: "bf16 slow here")
    policy = FlowPolicy(POLICY)
    with pytest.warns(RuntimeWarning, match="bf16 slow here"):
        policy.set_precision("bf16")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        policy.set_precision("fp32")  # float32 is never slowed by the cap
