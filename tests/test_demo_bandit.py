"""The core learns, through the same loop as MetaWorld runs: π-StepNFT on the toy bandit."""

import dataclasses

import pytest

from stepnft.demo_bandit import bandit_config, run_bandit_demo


def quiet(cfg):
    return run_bandit_demo(cfg, log=lambda s: None)


def with_algo(cfg, **changes):
    return dataclasses.replace(cfg, algo=dataclasses.replace(cfg.algo, **changes))


@pytest.fixture(scope="module")
def default_run():
    return quiet(bandit_config(iterations=12))


def test_sft_start_is_weak_and_stepnft_reaches_80(default_run):
    start = default_run["average"]["before"]
    validation = [r["charts/validation_success_rate"] for r in default_run["history"]
                  if r.get("charts/validation_success_rate") is not None]
    assert 0.15 <= start <= 0.5, start
    assert default_run["average"]["after"] >= 0.8 and max(validation) >= 0.8, validation


def test_ode_rollouts_give_no_signal():
    """Exploration ablation: with a = 0 the recorded steps are deterministic, E_pos = E_neg,
    and success does not rise."""
    run = quiet(with_algo(bandit_config(iterations=5), noise_level=0.0))
    updates = [r for r in run["history"] if "losses/E_pos" in r]
    assert updates and all(abs(r["losses/E_pos"] - r["losses/E_neg"]) < 1e-3 for r in updates)
    assert run["average"]["after"] < 0.6


def test_drift_guard_bounds_drift_under_aggressive_learning_rate():
    """Pitfall: with a large learning rate, many epochs and a slow EMA, ||v - v_old|| runs far
    past max_drift. The look-before-step guard keeps it near its limit."""
    base = bandit_config(iterations=6, eval=dataclasses.replace(bandit_config().eval, every=0))
    base = dataclasses.replace(base, sft=dataclasses.replace(base.sft, steps=500))
    aggressive = dict(lr=2e-3, update_epochs=8, ema_base=0.99, ema_target=0.999)
    free = quiet(with_algo(base, **aggressive))
    guarded = quiet(with_algo(base, drift_limit=0.25, **aggressive))
    free_max = max(r["losses/delta_v_norm"] for r in free["history"][1:])
    guarded_max = max(r["losses/delta_v_norm"] for r in guarded["history"][1:])
    assert free_max > 1.0, free_max
    assert guarded_max < 0.5 * free_max, (guarded_max, free_max)
    assert any(r["losses/drift_stopped"] for r in guarded["history"][1:])
