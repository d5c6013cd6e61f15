import math

import pytest
import torch

from stepnft.sampling import (ChunkSample, flow_matching_pair, sample_chunk, sde_step_coeffs, sde_step_log_prob,
                              sde_step_mean_std)


def reference_step(x_t, v, t, dt, a):
    """docs/algorithm.md §2 written out for scalars, independently of the implementation."""
    one_minus_t = dt if t == 1.0 else 1.0 - t
    sigma = a * math.sqrt(t / one_minus_t)
    u = (1 - sigma**2 * dt / (2 * t)) * x_t
    b = -dt * (1 + sigma**2 * (1 - t) / (2 * t))
    return u + b * v, sigma * math.sqrt(dt)


@pytest.mark.parametrize("t", [1.0, 0.75, 0.5, 0.25])
@pytest.mark.parametrize("a", [0.2, 0.7])
def test_sde_step_matches_spec(t, a):
    gen = torch.Generator().manual_seed(0)
    x_t, v = torch.randn(3, 2, 4, generator=gen), torch.randn(3, 2, 4, generator=gen)
    tt, dt = torch.full((3,), t), torch.full((3,), 0.25)
    mean, std = sde_step_mean_std(x_t, v, tt, dt, a)
    for i in range(3):
        for h in range(2):
            for k in range(4):
                m_ref, s_ref = reference_step(x_t[i, h, k].item(), v[i, h, k].item(), t, 0.25, a)
                assert mean[i, h, k].item() == pytest.approx(m_ref, rel=1e-5, abs=1e-6)
                assert std.expand_as(mean)[i, h, k].item() == pytest.approx(s_ref, rel=1e-5)


def test_first_step_sigma_uses_dt():
    _, _, std = sde_step_coeffs(torch.tensor([1.0]), torch.tensor([0.25]), 0.2)
    # sigma = a * sqrt(1 / d) = 0.4, std = sigma * sqrt(d) = 0.2
    assert std.item() == pytest.approx(0.2, rel=1e-6)


def test_zero_noise_is_euler():
    x_t, v = torch.randn(5, 4, 3), torch.randn(5, 4, 3)
    t, dt = torch.tensor([1.0, 0.75, 0.5, 0.25, 0.6]), torch.full((5,), 0.25)
    mean, std = sde_step_mean_std(x_t, v, t, dt, 0.0)
    torch.testing.assert_close(mean, x_t - dt.view(-1, 1, 1) * v)
    assert torch.all(std == 0)


def gaussian_velocity(mu, s):
    """Exact flow-matching velocity E[eps - x0 | x_t] for x0 ~ N(mu, s^2), eps ~ N(0, 1)."""

    def v(x, t):
        t = t.view(-1, 1, 1)
        var = (1 - t) ** 2 * s**2 + t**2
        centred = x - (1 - t) * mu
        e_x0 = mu + (1 - t) * s**2 / var * centred
        e_eps = t / var * centred
        return e_eps - e_x0

    return v


@pytest.mark.parametrize("noise_level", [0.0, 0.3])
def test_sde_preserves_marginals(noise_level):
    mu, s = 0.7, 0.5
    gen = torch.Generator().manual_seed(0)
    out = sample_chunk(gaussian_velocity(mu, s), (40_000, 1, 1), num_steps=200, noise_level=noise_level, generator=gen)
    x0 = out.actions.flatten()
    assert x0.mean().item() == pytest.approx(mu, abs=0.02)
    assert x0.std().item() == pytest.approx(s, rel=0.05)


def test_sde_without_correction_would_fail():
    """The test above can fail: a plain Euler step plus noise inflates the variance."""
    mu, s, K = 0.7, 0.5, 200
    gen = torch.Generator().manual_seed(0)
    v = gaussian_velocity(mu, s)
    x = torch.randn(40_000, 1, 1, generator=gen)
    for k in range(K):
        t = torch.full((x.shape[0],), 1 - k / K)
        x = x - v(x, t) / K + 0.3 * math.sqrt(1 / K) * torch.randn(x.shape, generator=gen)
    assert x.flatten().std().item() > 1.1 * s


def test_sample_chunk_records_one_step():
    calls = []

    def v(x, t):
        calls.append((x.clone(), t.clone()))
        return 0.5 * x

    out = sample_chunk(v, (64, 3, 2), num_steps=4, noise_level=0.2, generator=torch.Generator().manual_seed(1))
    assert isinstance(out, ChunkSample) and out.actions.shape == (64, 3, 2)
    assert set(out.step.tolist()) <= {0, 1, 2, 3} and len(set(out.step.tolist())) == 4
    for i in range(64):
        j = out.step[i].item()
        x_j, t_j = calls[j]
        torch.testing.assert_close(out.x_t[i], x_j[i])
        torch.testing.assert_close(out.v_old[i], 0.5 * x_j[i])
        assert out.t[i].item() == pytest.approx(1 - j / 4) == t_j[i].item()
        nxt = calls[j + 1][0][i] if j < 3 else out.actions[i]
        torch.testing.assert_close(out.x_next[i], nxt)
    assert torch.all(out.dt == 0.25)


def test_ode_sampling_is_deterministic_given_seed_and_one_step_mode():
    v = lambda x, t: x  # noqa: E731
    a = sample_chunk(v, (8, 2, 2), noise_level=0.0, generator=torch.Generator().manual_seed(3))
    b = sample_chunk(v, (8, 2, 2), noise_level=0.0, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(a.actions, b.actions)
    one = sample_chunk(v, (256, 2, 2), noise_level=0.5, stochastic_steps="one", generator=torch.Generator().manual_seed(3))
    # Every step but the recorded one is the Euler step, so the recorded one alone adds noise.
    ode_next = one.x_t - one.dt.view(-1, 1, 1) * one.v_old
    assert (one.x_next - ode_next).abs().mean() > 0.05


def test_flow_matching_pair():
    x0, eps, t = torch.ones(2, 1, 1), torch.zeros(2, 1, 1), torch.tensor([0.25, 1.0])
    x_t, v = flow_matching_pair(x0, t, eps)
    torch.testing.assert_close(x_t.flatten(), torch.tensor([0.75, 0.0]))
    torch.testing.assert_close(v.flatten(), torch.tensor([-1.0, -1.0]))


def test_keep_path_gives_every_step_consistently():
    v = lambda x, t: 0.3 * x + t.view(-1, 1, 1)  # noqa: E731
    out = sample_chunk(v, (5, 2, 3), num_steps=4, noise_level=0.4, generator=torch.Generator().manual_seed(2), keep_path=True)
    steps = out.all_steps()
    assert steps["x_t"].shape == (20, 2, 3) and steps["sample"].tolist() == [i for i in range(5) for _ in range(4)]
    torch.testing.assert_close(out.path_x[:, -1], out.actions)
    for i in range(5):
        j = out.step[i].item()
        row = 4 * i + j
        torch.testing.assert_close(steps["x_t"][row], out.x_t[i])
        torch.testing.assert_close(steps["x_next"][row], out.x_next[i])
        torch.testing.assert_close(steps["v_old"][row], out.v_old[i])
        assert steps["t"][row].item() == pytest.approx(out.t[i].item())
    torch.testing.assert_close(steps["v_old"], v(steps["x_t"], steps["t"]))
    with pytest.raises(ValueError, match="keep_path"):
        sample_chunk(v, (2, 2, 3)).all_steps()


def test_sde_step_log_prob_equals_an_independent_gaussian_density():
    """Each stochastic entry: -(x - m)^2 / (2 s^2) - log s - log(2π) / 2 with m, s from the scalar
    reference step; summed over action dims and the masked positions only."""
    gen = torch.Generator().manual_seed(0)
    b, h, a, noise = 4, 3, 2, 0.3
    x_t, v = torch.randn(b, h, a, generator=gen), torch.randn(b, h, a, generator=gen)
    t, dt = torch.tensor([1.0, 0.75, 0.5, 0.25]), torch.full((b,), 0.25)
    x_next = torch.randn(b, h, a, generator=gen)
    mask = torch.tensor([[1, 1, 1], [1, 1, 0], [1, 0, 0], [0, 0, 0]], dtype=torch.bool)
    got = sde_step_log_prob(x_next, x_t, v, t, dt, noise, mask)
    for i in range(b):
        want = 0.0
        for j in range(h):
            for k in range(a):
                if mask[i, j]:
                    m, s = reference_step(x_t[i, j, k].item(), v[i, j, k].item(), t[i].item(), 0.25, noise)
                    want += -((x_next[i, j, k].item() - m) ** 2) / (2 * s**2) - math.log(s) - 0.5 * math.log(2 * math.pi)
        assert got[i].item() == pytest.approx(want, rel=1e-5, abs=1e-5)
    assert got[3].item() == 0.0
    full = sde_step_log_prob(x_next, x_t, v, t, dt, noise)
    assert full[0].item() == pytest.approx(got[0].item()) and full[3].item() != 0.0  # no mask: every position counts


def test_sde_step_log_prob_of_deterministic_steps_is_zero_with_finite_gradient():
    x_t = torch.randn(3, 2, 2)
    v = torch.randn(3, 2, 2, requires_grad=True)
    t, dt = torch.tensor([1.0, 0.5, 0.25]), torch.full((3,), 0.25)
    x_next = x_t - 0.25 * v.detach() + 0.1  # off the Euler step: a density would be -inf
    logp = sde_step_log_prob(x_next, x_t, v, t, dt, 0.0)
    assert torch.all(logp == 0)
    logp.sum().backward()
    assert torch.all(torch.isfinite(v.grad)) and torch.all(v.grad == 0)


def test_sde_step_log_prob_is_highest_at_the_mean_and_its_gradient_moves_the_mean_toward_the_sample():
    gen = torch.Generator().manual_seed(1)
    x_t, v = torch.randn(1, 2, 2, generator=gen), torch.randn(1, 2, 2, generator=gen)
    t, dt = torch.tensor([0.5]), torch.tensor([0.25])
    mean, std = sde_step_mean_std(x_t, v, t, dt, 0.4)
    x_next = mean + std * torch.randn(1, 2, 2, generator=gen)
    assert sde_step_log_prob(mean, x_t, v, t, dt, 0.4) > sde_step_log_prob(x_next, x_t, v, t, dt, 0.4)
    v = v.clone().requires_grad_(True)
    sde_step_log_prob(x_next, x_t, v, t, dt, 0.4).sum().backward()
    new_mean, _ = sde_step_mean_std(x_t, v.detach() + 1e-3 * v.grad, t, dt, 0.4)
    assert (x_next - new_mean).norm() < (x_next - mean).norm()


@pytest.mark.parametrize("t", [1.0, 0.5, 0.25])
def test_without_mean_correction_the_noise_is_added_to_the_euler_step(t):
    x_t, v = torch.randn(4, 2, 3), torch.randn(4, 2, 3)
    tt, dt = torch.full((4,), t), torch.full((4,), 0.25)
    mean, std = sde_step_mean_std(x_t, v, tt, dt, 0.5, mean_correction=False)
    corrected, corrected_std = sde_step_mean_std(x_t, v, tt, dt, 0.5)
    torch.testing.assert_close(mean, x_t - 0.25 * v)
    torch.testing.assert_close(std, corrected_std)  # same noise, only the drift differs
    assert not torch.allclose(mean, corrected)


def test_sample_chunk_without_mean_correction_draws_around_the_euler_mean():
    velocity = lambda x, t: 0.3 * x + 1.0  # noqa: E731
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    plain = sample_chunk(velocity, (64, 2, 3), noise_level=0.5, generator=g1, keep_path=True, mean_correction=False)
    corrected = sample_chunk(velocity, (64, 2, 3), noise_level=0.5, generator=g2, keep_path=True)
    steps = plain.all_steps()
    mean, std = sde_step_mean_std(steps["x_t"], steps["v_old"], steps["t"], steps["dt"], 0.5, mean_correction=False)
    z = (steps["x_next"] - mean) / std
    assert abs(z.mean().item()) < 0.1 and z.std().item() == pytest.approx(1.0, abs=0.1)
    torch.testing.assert_close(plain.path_x[:, 0], corrected.path_x[:, 0])  # the same start
    assert not torch.allclose(plain.actions, corrected.actions)
