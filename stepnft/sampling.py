"""ODE and Flow-SDE denoising steps and chunk samplers (docs/algorithm.md §1–3). Pure functions.

Convention: ``x_t = (1 - t) * x0 + t * eps``; ``t = 1`` is pure noise, ``t = 0`` the action.
A chunk is denoised over ``K`` steps on the grid ``t_k = 1 - k / K``; step ``k`` goes from
``t_k`` to ``t_k - dt`` with ``dt = 1 / K``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch import Tensor

VelocityFn = Callable[[Tensor, Tensor], Tensor]
"""``velocity_fn(x_t [B, H, A], t [B]) -> v [B, H, A]`` with the observation bound inside."""


def _col(x: Tensor) -> Tensor:
    """``[B] -> [B, 1, 1]`` so per-sample scalars broadcast over a chunk ``[B, H, A]``."""
    return x.reshape(-1, 1, 1)


def sde_step_coeffs(t: Tensor, dt: Tensor, noise_level: float,
                    mean_correction: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    """Coefficients of one Flow-SDE step: ``mean = u * x_t + b * v``, ``x_next ~ N(mean, std^2)``.

    ``t``, ``dt``: ``[B]``. Returns ``u``, ``b``, ``std``, each ``[B, 1, 1]``.
    ``sigma_t = a * sqrt(t / (1 - t))``; at ``t = 1`` the denominator is ``dt`` (docs/algorithm.md §2).
    ``mean_correction=False`` is the paper's exploration ablation: the same noise added to the
    plain Euler step (``u = 1``, ``b = -dt``), without the drift terms that keep the marginals
    of the flow; the chunks then leave the distribution the policy was trained on.
    """
    t, dt = _col(t), _col(dt)
    one_minus_t = torch.where(t >= 1.0 - 1e-6, dt, 1.0 - t)
    sigma_sq = noise_level**2 * t / one_minus_t
    std = torch.sqrt(sigma_sq * dt)
    if not mean_correction:
        return torch.ones_like(t), -dt, std
    u = 1.0 - sigma_sq * dt / (2.0 * t)
    b = -dt * (1.0 + sigma_sq * (1.0 - t) / (2.0 * t))
    return u, b, std


def sde_step_mean_std(x_t: Tensor, v: Tensor, t: Tensor, dt: Tensor, noise_level: float,
                      mean_correction: bool = True) -> tuple[Tensor, Tensor]:
    """Mean and std of the Flow-SDE step ``x_t -> x_{t-dt}`` (docs/algorithm.md §2).

    ``x_t``, ``v``: ``[B, H, A]``; ``t``, ``dt``: ``[B]``. ``std`` is ``[B, 1, 1]``.
    ``noise_level = 0`` gives the Euler ODE step ``x_t - dt * v`` with ``std = 0``;
    ``mean_correction=False`` the Euler mean with the same ``std`` (an ablation, :func:`sde_step_coeffs`).
    """
    u, b, std = sde_step_coeffs(t, dt, noise_level, mean_correction)
    return u * x_t + b * v, std


def sde_step_log_prob(x_next: Tensor, x_t: Tensor, v: Tensor, t: Tensor, dt: Tensor, noise_level: float,
                      mask: Tensor | None = None) -> Tensor:
    """Log-density ``[B]`` of ``x_next`` under the Flow-SDE step ``N(mean, std^2 I)`` from
    ``(x_t, v)`` (the PPO/GRPO likelihood, docs/algorithm.md §7), summed over the action dims and
    the chunk positions ``mask`` ``[B, H]`` marks (None: all).

    A step with ``std = 0`` (``noise_level = 0``) is deterministic: it has no density and adds
    0 (with a finite, zero gradient), so only the stochastic steps of a chain count.
    """
    mean, std = sde_step_mean_std(x_t, v, t, dt, noise_level)
    stochastic = std > 0
    safe_std = torch.where(stochastic, std, torch.ones_like(std))  # no 0/0 in value or gradient
    per_entry = -0.5 * ((x_next - mean) / safe_std).pow(2) - safe_std.log() - 0.5 * math.log(2 * math.pi)
    per_position = (per_entry * stochastic).sum(dim=-1)  # [B, H]
    if mask is not None:
        per_position = per_position * mask.to(per_position.dtype)
    return per_position.sum(dim=-1)


def flow_matching_pair(actions: Tensor, t: Tensor, noise: Tensor) -> tuple[Tensor, Tensor]:
    """Noisy chunk and flow-matching target: ``x_t = (1-t) x0 + t eps``, ``v = eps - x0``."""
    return (1.0 - _col(t)) * actions + _col(t) * noise, noise - actions


def sample_flow_time(batch: int, generator: torch.Generator | None = None, law: str = "uniform") -> Tensor:
    """Training times ``t`` ``[B]`` for the SFT loss: ``uniform`` on (0, 1) or ``beta`` (π0's
    Beta(1.5, 1) law on the noise side, which weights the noisier times more)."""
    if law == "uniform":
        return torch.rand(batch, generator=generator).clamp(1e-3, 1.0)
    if law == "beta":
        # Beta(1.5, 1) by inversion: F(x) = x^1.5.
        u = torch.rand(batch, generator=generator) ** (1.0 / 1.5)
        return (0.001 + 0.999 * u).clamp(max=1.0)
    raise ValueError(f"unknown time law {law!r}; use 'uniform' or 'beta'")


@dataclass
class ChunkSample:
    """A sampled action chunk and the one recorded denoising step training needs (docs/algorithm.md §3).

    Shapes: ``actions``, ``x_t``, ``x_next``, ``v_old``: ``[B, H, A]``; ``step``, ``t``, ``dt``: ``[B]``.
    """

    actions: Tensor
    step: Tensor
    x_t: Tensor
    x_next: Tensor
    t: Tensor
    dt: Tensor
    v_old: Tensor
    path_x: Tensor | None = None
    """``[B, K + 1, H, A]``: the chunk at every grid time ``t_k`` (only with ``keep_path``)."""
    path_v: Tensor | None = None
    """``[B, K, H, A]``: the velocity used at every step (only with ``keep_path``)."""

    def recorded_steps(self, every_step: bool) -> dict[str, Tensor]:
        """The transitions a rollout stores: the one recorded step per sample, or (``every_step``)
        all K of :meth:`all_steps`; ``call`` [N] is each transition's sample row."""
        if every_step:
            steps = self.all_steps()
            steps["call"] = steps.pop("sample")
            return steps
        return {"x_t": self.x_t, "x_next": self.x_next, "v_old": self.v_old, "t": self.t, "dt": self.dt,
                "call": torch.arange(len(self.t), device=self.t.device)}

    def all_steps(self) -> dict[str, Tensor]:
        """Every denoising step as a transition, flattened to ``[B * K]`` (sample-major):
        ``x_t``, ``x_next``, ``v_old`` ``[B*K, H, A]``, ``t``, ``dt`` ``[B*K]``, ``sample`` (index)."""
        if self.path_x is None or self.path_v is None:
            raise ValueError("sample with keep_path=True to get every step")
        b, k = self.path_v.shape[:2]
        t = (1.0 - torch.arange(k, device=self.path_v.device) / k).repeat(b)
        return {
            "x_t": self.path_x[:, :-1].flatten(0, 1), "x_next": self.path_x[:, 1:].flatten(0, 1),
            "v_old": self.path_v.flatten(0, 1), "t": t, "dt": torch.full_like(t, 1.0 / k),
            "sample": torch.arange(b, device=self.path_v.device).repeat_interleave(k),
        }


Generators = torch.Generator | Sequence[torch.Generator] | None
"""One generator for the whole batch, or one per row (a row's draws then depend only on its
own generator: the same sample whatever the batch it is drawn in)."""


def _randn(shape: tuple[int, ...], generator: Generators) -> Tensor:
    if generator is None or isinstance(generator, torch.Generator):
        return torch.randn(shape, generator=generator)
    return torch.stack([torch.randn(shape[1:], generator=g) for g in generator])


def _randint(high: int, batch: int, generator: Generators) -> Tensor:
    if generator is None or isinstance(generator, torch.Generator):
        return torch.randint(0, high, (batch,), generator=generator)
    return torch.cat([torch.randint(0, high, (1,), generator=g) for g in generator])


@torch.no_grad()
def sample_chunk(
    velocity_fn: VelocityFn,
    shape: tuple[int, int, int],
    num_steps: int = 4,
    noise_level: float = 0.0,
    generator: Generators = None,
    stochastic_steps: str = "all",
    device: torch.device | str = "cpu",
    keep_path: bool = False,
    mean_correction: bool = True,
) -> ChunkSample:
    """Denoise pure noise into an action chunk ``[B, H, A]`` in ``num_steps`` steps.

    ``noise_level = 0`` is the deterministic ODE sampler (evaluation); ``> 0`` is Flow-SDE
    (exploration). One step index ``j ~ Uniform{0..K-1}`` per sample is recorded.
    ``stochastic_steps``: ``"all"`` makes every step stochastic (π-StepNFT), ``"one"`` only
    the recorded step, the rest ODE (πRL's PPO/GRPO likelihood). ``keep_path`` also
    returns every intermediate chunk and velocity (``path_x``, ``path_v``). ``generator`` may
    be one per row of the batch. ``mean_correction=False``: the stochastic steps add their noise
    to the plain Euler mean (the exploration ablation of :func:`sde_step_coeffs`).
    """
    if stochastic_steps not in ("all", "one"):
        raise ValueError(f"stochastic_steps must be 'all' or 'one', got {stochastic_steps!r}")
    batch = shape[0]
    x = _randn(shape, generator).to(device)
    step = _randint(num_steps, batch, generator).to(device)
    dt = torch.full((batch,), 1.0 / num_steps, device=device)
    xs, vs = [x], []
    for k in range(num_steps):
        t = torch.full((batch,), 1.0 - k / num_steps, device=device)
        v = velocity_fn(x, t)
        mean, std = sde_step_mean_std(x, v, t, dt, noise_level, mean_correction)
        if stochastic_steps == "one":  # the other steps are plain Euler steps
            here = _col(step == k)
            ode_mean, _ = sde_step_mean_std(x, v, t, dt, 0.0)
            mean, std = torch.where(here, mean, ode_mean), std * here.float()
        x = mean + std * _randn(shape, generator).to(device)
        xs.append(x)
        vs.append(v)
    # The recorded step of each sample, gathered from the path (one index per sample).
    path_x, path_v = torch.stack(xs, dim=1), torch.stack(vs, dim=1)
    rows = torch.arange(batch, device=device)
    rec = {"x_t": path_x[rows, step], "x_next": path_x[rows, step + 1], "v_old": path_v[rows, step]}
    if keep_path:
        rec["path_x"], rec["path_v"] = path_x, path_v
    grid = torch.tensor([1.0 - k / num_steps for k in range(num_steps)], device=device)  # the t of each step
    return ChunkSample(actions=x, step=step, t=grid[step], dt=dt, **rec)
