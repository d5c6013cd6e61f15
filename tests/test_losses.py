import pytest
import torch

from stepnft.losses import flow_matching_loss, stepnft_loss
from stepnft.sampling import sde_step_coeffs, sde_step_mean_std


def make_batch(seed=0, b=6, h=3, a=4, drift=0.1):
    g = torch.Generator().manual_seed(seed)
    x_t = torch.randn(b, h, a, generator=g)
    v_old = torch.randn(b, h, a, generator=g)
    v = v_old + drift * torch.randn(b, h, a, generator=g)
    t = torch.tensor([1.0, 0.75, 0.5, 0.25, 0.75, 0.5])[:b]
    dt = torch.full((b,), 0.25)
    mean, std = sde_step_mean_std(x_t, v_old, t, dt, 0.2)
    x_next = mean + std * torch.randn(b, h, a, generator=g)
    y = torch.tensor([1.0, -1.0, 1.0, -1.0, 1.0, 1.0])[:b]
    return dict(v=v, v_old=v_old, x_t=x_t, x_next=x_next, t=t, dt=dt, y=y)


def energies(d, noise=0.2, beta=1.0, max_drift=0.5):
    _, met = stepnft_loss(d["v"], d["v_old"], d["x_t"], d["x_next"], d["t"], d["dt"], noise, d["y"], beta=beta, max_drift=max_drift)
    return met


def per_position_terms(d, noise=0.2, beta=1.0, max_drift=0.5):
    """E_pos, E_neg recomputed from docs/algorithm.md §4 by hand, plus B, rho, Δc, var."""
    u, b, std = sde_step_coeffs(d["t"], d["dt"], noise)
    var = std**2 + 1e-4
    delta = d["v"] - d["v_old"]
    norm = delta.norm(dim=-1, keepdim=True)
    delta_c = delta * torch.clamp(max_drift / norm, max=1.0)
    m_old = u * d["x_t"] + b * d["v_old"]
    m_pos, m_neg = m_old + beta * b * delta_c, m_old - beta * b * delta_c
    e_pos = ((d["x_next"] - m_pos) ** 2 / var).sum(-1)
    e_neg = ((d["x_next"] - m_neg) ** 2 / var).sum(-1)
    return e_pos, e_neg, b, d["x_next"] - m_old, delta_c, var


@pytest.mark.parametrize("beta", [1.0, 2.0])
@pytest.mark.parametrize("drift", [0.05, 3.0])
def test_energy_difference_identity(beta, drift):
    d = make_batch(drift=drift)
    e_pos, e_neg, b, rho, delta_c, var = per_position_terms(d, beta=beta)
    closed_form = (-4 * beta * b * (rho * delta_c) / var).sum(-1)
    torch.testing.assert_close(e_pos - e_neg, closed_form, rtol=1e-4, atol=1e-4)
    met = energies(d, beta=beta)
    assert met["E_pos"] == pytest.approx(e_pos.mean().item(), rel=1e-5)
    assert met["E_neg"] == pytest.approx(e_neg.mean().item(), rel=1e-5)


def test_rank_loss_value():
    d = make_batch()
    e_pos, e_neg, *_ = per_position_terms(d)
    expected = torch.nn.functional.softplus(0.5 * d["y"][:, None] * (e_pos - e_neg)).mean()
    expected = expected + 1e-4 * (d["v"] - d["v_old"]).pow(2).mean()
    loss, _ = stepnft_loss(d["v"], d["v_old"], d["x_t"], d["x_next"], d["t"], d["dt"], 0.2, d["y"])
    assert loss.item() == pytest.approx(expected.item(), rel=1e-5)


def test_wmse_equals_rank_linear_part_plus_implicit_penalty():
    d = make_batch(drift=0.3)
    common = dict(noise_level=0.2, y=d["y"], kl_beta=0.0, beta=1.5)
    args = (d["v"], d["v_old"], d["x_t"], d["x_next"], d["t"], d["dt"])
    wmse, _ = stepnft_loss(*args, form="wmse", **common)
    e_pos, e_neg, b, rho, delta_c, var = per_position_terms(d, beta=1.5)
    linear = 0.5 * d["y"][:, None] * (e_pos - e_neg)
    const = (rho**2 / var).sum(-1)
    penalty = (1.5**2 * b**2 * delta_c**2 / var).sum(-1)
    assert (wmse - (linear + const).mean()).item() == pytest.approx(penalty.mean().item(), rel=1e-4)
    assert penalty.mean().item() > 0


def test_drift_clip_caps_norm():
    d = make_batch(drift=5.0)
    _, met = stepnft_loss(d["v"], d["v_old"], d["x_t"], d["x_next"], d["t"], d["dt"], 0.2, d["y"], max_drift=0.5)
    *_, delta_c, _ = per_position_terms(d, max_drift=0.5)
    assert delta_c.norm(dim=-1).max().item() == pytest.approx(0.5, rel=1e-4)
    assert met["drift_clip_frac"] == 1.0 and met["delta_v_norm"] > 0.5
    small = make_batch(drift=1e-3)
    _, met_small = stepnft_loss(small["v"], small["v_old"], small["x_t"], small["x_next"], small["t"], small["dt"], 0.2, small["y"])
    assert met_small["drift_clip_frac"] == 0.0


def test_zero_drift_has_finite_gradient():
    d = make_batch()
    v = d["v_old"].clone().requires_grad_(True)
    loss, _ = stepnft_loss(v, d["v_old"], d["x_t"], d["x_next"], d["t"], d["dt"], 0.2, d["y"])
    loss.backward()
    assert torch.isfinite(v.grad).all()


@pytest.mark.parametrize("label", [1.0, -1.0])
def test_gradient_step_moves_mean_toward_or_away_from_sample(label):
    d = make_batch(b=4, drift=0.0)
    d["y"] = torch.full((4,), label)
    d["t"], d["dt"] = torch.full((4,), 0.75), torch.full((4,), 0.25)
    v = (d["v_old"] + 1e-3).clone().requires_grad_(True)  # start just off v_old
    def dist(vel):
        mean, _ = sde_step_mean_std(d["x_t"], vel, d["t"], d["dt"], 0.2)
        return (mean - d["x_next"]).pow(2).sum()
    before = dist(v.detach())
    loss, _ = stepnft_loss(v, d["v_old"], d["x_t"], d["x_next"], d["t"], d["dt"], 0.2, d["y"], kl_beta=0.0)
    loss.backward()
    after = dist(v.detach() - 1e-3 * v.grad)
    assert (after < before) if label > 0 else (after > before)


def test_mask_excludes_positions_and_x0_target():
    d = make_batch()
    mask = torch.tensor([[True, False, False]] * 6)
    args = (d["v"], d["v_old"], d["x_t"], d["x_next"], d["t"], d["dt"], 0.2, d["y"])
    masked, _ = stepnft_loss(*args, mask=mask)
    first_only, _ = stepnft_loss(d["v"][:, :1], d["v_old"][:, :1], d["x_t"][:, :1], d["x_next"][:, :1], d["t"], d["dt"], 0.2, d["y"])
    assert masked.item() == pytest.approx(first_only.item(), rel=1e-5)

    actions = torch.randn_like(d["x_t"])
    x0, met = stepnft_loss(*args, target="x0", actions=actions, kl_beta=0.0)
    _, _, std = sde_step_coeffs(d["t"], d["dt"], 0.2)
    var = std**2 + 1e-4
    t = d["t"].view(-1, 1, 1)
    delta = d["v"] - d["v_old"]
    delta_c = delta * torch.clamp(0.5 / delta.norm(dim=-1, keepdim=True), max=1.0)
    e_pos = ((actions - (d["x_t"] - t * (d["v_old"] + delta_c))) ** 2 / var).sum(-1)
    assert met["E_pos"] == pytest.approx(e_pos.mean().item(), rel=1e-5)
    with pytest.raises(ValueError, match="actions"):
        stepnft_loss(*args, target="x0")


def test_weights_change_balance():
    d = make_batch()
    args = (d["v"], d["v_old"], d["x_t"], d["x_next"], d["t"], d["dt"], 0.2, d["y"])
    only_first = torch.tensor([1.0, 0, 0, 0, 0, 0])
    weighted, _ = stepnft_loss(*args, weight=only_first, kl_beta=0.0)
    single, _ = stepnft_loss(*(a[:1] if torch.is_tensor(a) else a for a in args), kl_beta=0.0)
    assert weighted.item() == pytest.approx(single.item(), rel=1e-5)


def test_flow_matching_loss_known_value():
    pred, target = torch.zeros(2, 2, 3), torch.ones(2, 2, 3)
    assert flow_matching_loss(pred, target).item() == pytest.approx(3.0)
    mask = torch.tensor([[True, False], [True, False]])
    target[:, 1] = 10.0
    assert flow_matching_loss(pred, target, mask).item() == pytest.approx(3.0)


def test_clipped_policy_loss_clips_the_ratio_on_the_side_the_advantage_pushes():
    from stepnft.losses import clipped_policy_loss

    old = torch.zeros(4)
    log_prob = torch.log(torch.tensor([1.5, 1.5, 0.5, 1.0])).requires_grad_(True)
    adv = torch.tensor([1.0, -1.0, -1.0, 2.0])
    loss, metrics = clipped_policy_loss(log_prob, old, adv, clip_coef=0.2)
    # min(r A, clip(r) A) per sample: 1.2 (clipped), -1.5, -0.8 (clipped), 2.0; loss = -mean.
    assert loss.item() == pytest.approx(-(1.2 - 1.5 - 0.8 + 2.0) / 4)
    assert metrics["clipfrac"] == pytest.approx(0.75)
    ratio = torch.tensor([1.5, 1.5, 0.5, 1.0])
    assert metrics["approx_kl"] == pytest.approx(((ratio - 1) - ratio.log()).mean().item())
    loss.backward()
    # Clipped samples get no gradient; the others -A r / 4.
    torch.testing.assert_close(log_prob.grad, torch.tensor([0.0, 1.5 / 4, 0.0, -2.0 / 4]))


def test_branch_forms_are_the_two_halves_of_wmse():
    d = make_batch(drift=0.3)
    d["y"] = torch.tensor([1.0, -1.0, 0.5, -0.2, 1.0, -1.0])  # progress labels lie in [-1, 1]
    args = (d["v"], d["v_old"], d["x_t"], d["x_next"], d["t"], d["dt"], 0.2, d["y"])
    e_pos, e_neg, *_ = per_position_terms(d)
    r = 0.5 * (d["y"][:, None] + 1)
    pos, _ = stepnft_loss(*args, form="pos", kl_beta=0.0)
    neg, _ = stepnft_loss(*args, form="neg", kl_beta=0.0)
    wmse, _ = stepnft_loss(*args, form="wmse", kl_beta=0.0)
    assert pos.item() == pytest.approx((r * e_pos).mean().item(), rel=1e-5)
    assert neg.item() == pytest.approx(((1 - r) * e_neg).mean().item(), rel=1e-5)
    assert (pos + neg).item() == pytest.approx(wmse.item(), rel=1e-5)
    with pytest.raises(ValueError, match="'pos' or 'neg'"):
        stepnft_loss(*args, form="both")


def test_without_mean_correction_the_candidates_are_euler_means():
    d = make_batch(drift=0.3)
    args = (d["v"], d["v_old"], d["x_t"], d["x_next"], d["t"], d["dt"], 0.2, d["y"])
    _, met = stepnft_loss(*args, mean_correction=False, max_drift=None)
    col = d["dt"].view(-1, 1, 1)
    _, _, std = sde_step_coeffs(d["t"], d["dt"], 0.2)
    var = std**2 + 1e-4
    e_pos = ((d["x_next"] - (d["x_t"] - col * d["v"])) ** 2 / var).sum(-1)  # v_+ = v_old + Δ = v (β = 1)
    assert met["E_pos"] == pytest.approx(e_pos.mean().item(), rel=1e-5)
    assert met["E_pos"] != pytest.approx(energies(d, max_drift=None)["E_pos"], rel=1e-3)
