"""benchmarks/vla_compute.py: every algorithm gets the same policy calls, and the ratios the
issue's targets read are the right way round."""

import pytest
from benchmark_loader import benchmark_module


@pytest.fixture(scope="module")
def vla_compute():
    with benchmark_module("vla_compute") as module:
        yield module


def row(algo, precision, checkpointing, seconds, memory, weights=100.0):
    return {"algo": algo, "precision": precision, "gradient_checkpointing": checkpointing,
            "update_s_per_sample": seconds, "update_cpu_s_per_sample": 2 * seconds, "update_peak_MB": memory,
            "peak_MB": memory + 1000, "weights_MB": weights}


def test_every_algorithm_is_measured_in_every_precision_with_checkpointing_and_lora(vla_compute):
    cases = set(vla_compute.CASES)
    assert len(cases) == len(vla_compute.CASES)
    assert {(a, p, False, 0) for a in vla_compute.ALGOS for p in ("fp32", "bf16")} <= cases
    assert {(a, "bf16", True, 0) for a in vla_compute.ALGOS} <= cases
    assert {(a, "bf16", True, vla_compute.LORA_RANK) for a in vla_compute.ALGOS} <= cases
    assert vla_compute.LORA_RANK > 0


def test_lora_rows_are_named_and_left_out_of_the_expert_only_ratios(vla_compute):
    rows = [row("stepnft", "bf16", False, 1.0, 400.0), row("ppo", "bf16", False, 3.0, 1000.0),
            row("stepnft", "bf16", True, 2.0, 100.0) | {"lora_rank": 16, "trained_M": 12.5}]
    r = vla_compute.ratios(rows)
    assert r["stepnft_vs_ppo_throughput_bf16"] == pytest.approx(3.0)
    assert "checkpointing_vs_not_update_memory_stepnft" not in r  # the only checkpointed row is a LoRA one
    assert "LoRA 16 + expert (12.5 M)" in vla_compute.table(rows)


def test_ratios_read_the_targets_the_right_way_round(vla_compute):
    rows = [row("stepnft", "fp32", False, 1.0, 400.0, weights=1800.0), row("ppo", "fp32", False, 3.0, 1000.0),
            row("stepnft", "bf16", False, 0.5, 300.0, weights=1100.0), row("ppo", "bf16", False, 2.0, 600.0),
            row("stepnft", "bf16", True, 0.7, 150.0), {"algo": "grpo", "precision": "fp32",
                                                       "gradient_checkpointing": False, "error": "x"}]
    r = vla_compute.ratios(rows)
    assert r["stepnft_vs_ppo_throughput_fp32"] == pytest.approx(3.0)  # PPO's seconds / π-StepNFT's
    assert r["stepnft_vs_ppo_update_memory_fp32"] == pytest.approx(0.4)  # π-StepNFT's memory / PPO's
    assert r["stepnft_vs_ppo_throughput_bf16"] == pytest.approx(4.0)
    assert r["bf16_vs_fp32_weights"] == pytest.approx(1100 / 1800)
    assert r["checkpointing_vs_not_update_memory_stepnft"] == pytest.approx(0.5)
    table = vla_compute.table(rows)
    assert table.count("\n") == len(rows) + 1 and "error: x" in table


def test_tiled_init_fills_random_weights_at_scale_keeps_constant_ones_and_restores_torch(vla_compute):
    import torch

    originals = torch.nn.init.normal_, torch.nn.init.kaiming_uniform_
    with vla_compute.tiled_init(std=0.02):
        linear, norm = torch.nn.Linear(300, 200), torch.nn.LayerNorm(300)
        embed = torch.nn.Embedding(vla_compute.TILE // 64 + 5, 128)  # more values than the block: tiled
        skewed = torch.empty(40, 30).t()  # not contiguous
        torch.nn.init.normal_(skewed, std=5.0)
    assert (torch.nn.init.normal_, torch.nn.init.kaiming_uniform_) == originals
    assert torch.isfinite(linear.weight).all() and 0.015 < linear.weight.std().item() < 0.025
    assert linear.weight.abs().max() > 0 and not torch.equal(linear.weight[0], linear.weight[1])
    assert torch.equal(norm.weight, torch.ones(300)) and torch.equal(norm.bias, torch.zeros(300))
    flat = embed.weight.detach().view(-1)
    assert torch.equal(flat[vla_compute.TILE:vla_compute.TILE + 320], flat[:320])  # the block repeats
    assert torch.isfinite(skewed).all() and 0.015 < skewed.std().item() < 0.025
    fresh = torch.nn.Linear(300, 200)  # outside: torch's own kaiming init again
    assert fresh.weight.abs().max() <= (1 / 300) ** 0.5 + 1e-6
