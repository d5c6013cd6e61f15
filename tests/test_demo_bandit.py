"""Proof that the core learns (issue: core library, item 6) and the ablation switches run."""

import pytest

from stepnft.demo_bandit import BanditDemoConfig, run_bandit_demo, with_overrides


@pytest.fixture(scope="module")
def default_history():
    return run_bandit_demo(BanditDemoConfig(), log=lambda s: None)


def test_sft_start_is_weak_and_stepnft_reaches_80(default_history):
    start = default_history[0]["success"]
    final = sum(r["success"] for r in default_history[-3:]) / 3
    assert 0.15 <= start <= 0.5, start
    assert final >= 0.8, final


def test_ode_rollouts_give_no_signal():
    """Exploration ablation: with a = 0 the recorded step is deterministic, E_pos = E_neg."""
    hist = run_bandit_demo(with_overrides(BanditDemoConfig(iterations=5), noise_level=0.0), log=lambda s: None)
    assert all(abs(r["E_pos"] - r["E_neg"]) < 1e-3 for r in hist[1:])
    assert hist[-1]["success"] < 0.6


@pytest.mark.parametrize("switch", [dict(target="x0"), dict(form="wmse"), dict(beta=2.0), dict(label_balance="global")])
def test_ablation_switches_run_and_report(switch):
    hist = run_bandit_demo(with_overrides(BanditDemoConfig(iterations=8), **switch), log=lambda s: None)
    assert len(hist) == 9
    for key in ("E_pos", "E_neg", "delta_v_norm", "drift_clip_frac", "kl", "loss"):
        assert key in hist[-1]
    assert 0.0 <= hist[-1]["success"] <= 1.0
