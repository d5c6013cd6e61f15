"""π-StepNFT objective, its ablations, PPO's clipped surrogate and the flow-matching SFT loss
(docs/algorithm.md §1, §4, §6, §7).

Pure functions that return ``(loss, metrics)``: ``metrics`` holds every named term as a
detached float so trainers can log them and tests can check them.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from stepnft.sampling import sde_step_coeffs

_EPS = 1e-12  # inside the square root: ||Δ|| at Δ = 0 would have a NaN gradient


def _masked_mean(per_position: Tensor, mask: Tensor, weight: Tensor | None = None) -> Tensor:
    """Mean over valid chunk positions of each sample, then (weighted) mean over samples.

    ``per_position``, ``mask``: ``[B, H]``; ``weight``: ``[B]`` or None.
    """
    mask = mask.to(per_position.dtype)
    count = mask.sum(dim=1)
    per_sample = (per_position * mask).sum(dim=1) / count.clamp(min=1.0)
    w = (count > 0).to(per_position.dtype)
    if weight is not None:
        w = w * weight
    return (per_sample * w).sum() / w.sum().clamp(min=_EPS)


def stepnft_loss(
    v: Tensor,
    v_old: Tensor,
    x_t: Tensor,
    x_next: Tensor,
    t: Tensor,
    dt: Tensor,
    noise_level: float,
    y: Tensor,
    beta: float = 1.0,
    beta_dpo: float = 1.0,
    max_drift: float | None = 0.5,
    kl_beta: float = 1e-4,
    mask: Tensor | None = None,
    *,
    target: str = "next",
    form: str = "rank",
    actions: Tensor | None = None,
    weight: Tensor | None = None,
    mean_correction: bool = True,
) -> tuple[Tensor, dict[str, float]]:
    """The π-StepNFT step-wise contrastive ranking loss (docs/algorithm.md §4). One function on
    purpose: the body reads as the equations of §4 top to bottom (its length is the signature
    and this argument list).

    Args:
        v: policy velocity at ``(x_t, t)``, with grad, ``[B, H, A]``.
        v_old: rollout (EMA) policy's velocity at the same point, ``[B, H, A]``.
        x_t, x_next: the recorded stochastic step ``x_t -> x_{t-dt}``, ``[B, H, A]``.
        t, dt: ``[B]``. noise_level: the Flow-SDE ``a`` used in the rollout.
        y: ``[B]`` in {+1, -1}: episode success / failure.
        beta: trust factor of the mirrored candidates ``v_old ± β Δc``.
        beta_dpo: temperature of the ranking softplus.
        max_drift: cap on ``||Δ||`` per chunk position (norm over action dims); None disables.
        kl_beta: weight of the ``mean((v - v_old)^2)`` regulariser.
        mask: ``[B, H]`` bool, True on executed chunk positions; None means all.
        target: ``"next"`` (step-wise, the paper) or ``"x0"`` (ablation: compare
            ``x0_± = x_t - t v_±`` with ``actions``, the executed chunk, same normaliser).
        form: ``"rank"`` (the paper), ``"wmse"`` (DiffusionNFT-style ablation
            ``r E_pos + (1 - r) E_neg``, ``r = (y + 1) / 2``), or one branch of it alone:
            ``"pos"`` (``r E_pos``: pull toward successful steps) or ``"neg"``
            (``(1 - r) E_neg``: push away from failed ones).
        actions: the executed chunk ``[B, H, A]``; required when ``target="x0"``.
        weight: optional per-sample weights ``[B]`` (e.g. label balancing); None = uniform.
        mean_correction: the step coefficients the rollout sampled with (False: the plain
            Euler mean, the exploration ablation of ``sde_step_coeffs``).
    """
    if target not in ("next", "x0"):
        raise ValueError(f"target must be 'next' or 'x0', got {target!r}")
    if form not in ("rank", "wmse", "pos", "neg"):
        raise ValueError(f"form must be 'rank', 'wmse', 'pos' or 'neg', got {form!r}")
    if mask is None:
        mask = torch.ones(v.shape[:2], dtype=torch.bool, device=v.device)

    delta = v - v_old
    delta_norm = torch.sqrt(delta.pow(2).sum(dim=-1, keepdim=True) + _EPS)  # [B, H, 1]
    if max_drift is None:
        scale = torch.ones_like(delta_norm)
    else:
        scale = torch.clamp(max_drift / delta_norm, max=1.0)
    delta_c = delta * scale
    v_pos, v_neg = v_old + beta * delta_c, v_old - beta * delta_c

    u, b, std = sde_step_coeffs(t, dt, noise_level, mean_correction)
    var = std.detach().pow(2) + 1e-4  # [B, 1, 1]
    if target == "next":
        obs = x_next
        pred_pos, pred_neg = u * x_t + b * v_pos, u * x_t + b * v_neg
    else:
        if actions is None:
            raise ValueError("target='x0' needs the executed chunk: pass actions=...")
        obs = actions
        t_col = t.reshape(-1, 1, 1)
        pred_pos, pred_neg = x_t - t_col * v_pos, x_t - t_col * v_neg
    e_pos = ((obs - pred_pos).pow(2) / var).sum(dim=-1)  # [B, H]
    e_neg = ((obs - pred_neg).pow(2) / var).sum(dim=-1)

    y_col = y.to(v.dtype).reshape(-1, 1)
    r = 0.5 * (y_col + 1.0)
    if form == "rank":
        per_position = F.softplus(0.5 * beta_dpo * y_col * (e_pos - e_neg))
    elif form == "wmse":
        per_position = r * e_pos + (1.0 - r) * e_neg
    elif form == "pos":
        per_position = r * e_pos
    else:
        per_position = (1.0 - r) * e_neg
    main = _masked_mean(per_position, mask, weight)
    kl = _masked_mean(delta.pow(2).mean(dim=-1), mask, weight)
    loss = main + kl_beta * kl

    with torch.no_grad():
        m = mask.float()
        n = m.sum().clamp(min=1.0)
        metrics = {
            "loss": loss.item(),
            "loss_main": main.item(),
            "kl": kl.item(),
            "E_pos": ((e_pos * m).sum() / n).item(),
            "E_neg": ((e_neg * m).sum() / n).item(),
            "E_diff_signed": ((y_col * (e_pos - e_neg) * m).sum() / n).item(),
            "delta_v_norm": ((delta_norm.squeeze(-1) * m).sum() / n).item(),
            "drift_clip_frac": (((scale.squeeze(-1) < 1.0).float() * m).sum() / n).item(),
            "pos_frac": (y > 0).float().mean().item(),
        }
    return loss, metrics


def clipped_policy_loss(log_prob: Tensor, old_log_prob: Tensor, advantages: Tensor,
                        clip_coef: float) -> tuple[Tensor, dict[str, float]]:
    """PPO's clipped surrogate ``-mean(min(r A, clip(r, 1 - ε, 1 + ε) A))``, ``r = exp(log π - log π_old)``
    (docs/algorithm.md §7); all inputs ``[B]``, ``log_prob`` with grad.

    Metrics: ``policy_loss``, ``approx_kl`` (``mean((r - 1) - log r)``, unbiased, always >= 0),
    ``old_approx_kl`` (``mean(-log r)``), ``clipfrac`` (share of ratios outside the clip range),
    ``ratio_max``.
    """
    log_ratio = log_prob - old_log_prob
    ratio = log_ratio.exp()
    unclipped = -advantages * ratio
    clipped = -advantages * ratio.clamp(1.0 - clip_coef, 1.0 + clip_coef)
    loss = torch.max(unclipped, clipped).mean()
    with torch.no_grad():
        metrics = {
            "policy_loss": loss.item(),
            "approx_kl": ((ratio - 1.0) - log_ratio).mean().item(),
            "old_approx_kl": (-log_ratio).mean().item(),
            "clipfrac": ((ratio - 1.0).abs() > clip_coef).float().mean().item(),
            "ratio_max": ratio.max().item(),
        }
    return loss, metrics


def flow_matching_loss(v_pred: Tensor, v_target: Tensor, mask: Tensor | None = None) -> Tensor:
    """SFT flow-matching loss ``||v_θ(x_t, t) - (eps - x0)||^2`` (docs/algorithm.md §1).

    ``v_pred``, ``v_target``: ``[B, H, A]``; ``mask``: ``[B, H]`` (padded positions excluded).
    Squared error summed over action dims, averaged over valid positions.
    """
    per_position = (v_pred - v_target).pow(2).sum(dim=-1)
    if mask is None:
        return per_position.mean()
    m = mask.to(per_position.dtype)
    return (per_position * m).sum() / m.sum().clamp(min=1.0)
