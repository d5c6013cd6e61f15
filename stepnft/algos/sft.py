"""Few-shot behaviour cloning: the flow-matching loss over demonstration chunks
(docs/algorithm.md §1), and the SFT stage of a run in three steps, which :func:`sft_stage`
composes from the run's config sections:

    episodes = load_or_generate_demos(demos_cfg, env_cfg, simulator)     # data (stepnft.data.demos)
    data = sft_chunks(episodes, env_cfg, simulator, horizon)            # chunks at the policy's horizon
    fit_processor(policy, data, instructions)                           # fit
    losses = sft_train(policy, data, sft_cfg, generator)                # train
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Callable, ClassVar, Literal

import numpy as np
import torch
from tqdm.auto import tqdm

from stepnft.algos.base import RunDiverged
from stepnft.data.demos import DemoEpisode, demos_to_chunks, load_or_generate_demos
from stepnft.devices import to_device
from stepnft.envs import simulator_for
from stepnft.losses import flow_matching_loss
from stepnft.policies.base import Policy, load_policy, make_policy, non_finite_samples, probe_rows
from stepnft.policies.vision import random_shift
from stepnft.sampling import flow_matching_pair, sample_flow_time
from stepnft.settings import Range, Settings


@dataclass
class SFTConfig(Settings):
    """Hyperparameters of flow-matching behaviour cloning."""

    section: ClassVar[str] = "sft"

    steps: Annotated[int, Range(ge=0, le=10**8)] = 3000
    """Gradient steps."""
    batch_size: Annotated[int, Range(ge=1, le=2**20)] = 256
    """Chunks per gradient step."""
    lr: Annotated[float, Range(gt=0, le=1)] = 3e-4
    """AdamW learning rate."""
    adam_betas: tuple[Annotated[float, Range(ge=0, lt=1)], Annotated[float, Range(ge=0, lt=1)]] = (0.9, 0.999)
    """AdamW (beta1, beta2)."""
    adam_eps: Annotated[float, Range(gt=0, le=1)] = 1e-8
    """AdamW epsilon."""
    weight_decay: Annotated[float, Range(ge=0, le=1)] = 1e-4
    """AdamW weight decay."""
    time_law: Literal["uniform", "beta"] = "uniform"
    """Law of the flow time t during training: ``uniform`` or ``beta`` (π0's)."""
    image_shift: Annotated[int, Range(ge=0, le=64)] = 4
    """Random-shift augmentation of camera images (pixels, at the policy's image size): each
    image is padded by replication and cropped back at a random offset (0: off). SFT only: in
    RL updates v_old was computed on the unshifted views."""


def sft_train(
    policy: Policy,
    data: dict,
    cfg: SFTConfig,
    generator: torch.Generator | None = None,
    on_step: Callable[[int, float], None] | None = None,
) -> list[float]:
    """Fit ``policy`` to demonstration chunks; returns the loss of every step.

    ``data``: ``obs`` (raw observation dict, ``[N, ...]`` per key), ``actions`` [N, H, A] in
    [-1, 1], ``mask`` [N, H] (False on positions padded past an episode's end), on the CPU.
    Observations go through ``policy.processor`` (fit and bound beforehand). Each minibatch is
    drawn and noised on the CPU (from ``generator``), then moved to the policy's device.
    """
    optimizer = torch.optim.AdamW(policy.parameters(), lr=cfg.lr, betas=cfg.adam_betas, eps=cfg.adam_eps,
                                  weight_decay=cfg.weight_decay)
    n = data["actions"].shape[0]
    losses: list[float] = []
    policy.train()
    for step in range(cfg.steps):
        idx = torch.randint(0, n, (min(cfg.batch_size, n),), generator=generator)
        actions = policy.model_actions(data["actions"][idx])
        t = sample_flow_time(len(idx), generator, cfg.time_law)
        noise = torch.randn(actions.shape, generator=generator)
        x_t, v_target = flow_matching_pair(actions, t, noise)
        obs = policy.processor({k: v[idx] for k, v in data["obs"].items()})
        if "image" in obs:
            obs["image"] = random_shift(obs["image"], cfg.image_shift, generator)
        obs, x_t, t, v_target, mask = to_device((obs, x_t, t, v_target, data["mask"][idx]), policy.device)
        loss = flow_matching_loss(policy.velocity(obs, x_t, t), v_target, mask)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
        if on_step is not None:
            on_step(step, losses[-1])
    return losses


def sft_chunks(episodes: Sequence[DemoEpisode], env_cfg, simulator, horizon: int, only_successful: bool = True
               ) -> dict:
    """The SFT data of ``episodes`` for a policy of chunk length ``horizon`` on the env of
    ``env_cfg`` (an ``EnvConfig``): the part of each state its ``state_obs`` shows, its cameras'
    images; see ``stepnft.data.demos.demos_to_chunks`` for the keys and shapes."""
    return demos_to_chunks(episodes, simulator.validate_tasks(env_cfg.tasks), horizon, only_successful=only_successful,
                           state_fn=lambda states: simulator.policy_state(states, env_cfg.state_obs),
                           images=bool(env_cfg.cameras))


def fit_processor(policy: Policy, data: dict, instructions: list[str], cache_dir: str | Path | None = None,
                  keep_statistics: bool = False) -> None:
    """Fit ``policy.processor``'s state statistics to ``data["obs"]["state"]`` [N, S] and bind it
    to the tasks' ``instructions``. With ``keep_statistics`` (a saved policy SFT fine-tunes), a
    processor that has statistics keeps them."""
    if not keep_statistics or getattr(policy.processor, "needs_fit", False):
        policy.processor.fit(data["obs"]["state"])
    policy.processor.bind_instructions(instructions, cache_dir)


def sft_stage(env_cfg, demos_cfg, policy_cfg, sft_cfg: SFTConfig, *, seed: int, simulator=None, init: str | None = None,
              device: str = "cpu", cache_dir: str | Path | None = None, log: Callable[[str], None] = print,
              episodes: Sequence[DemoEpisode] | None = None, precision: str = "fp32",
              gradient_checkpointing: bool = False) -> Policy:
    """The SFT stage of a run from its ``EnvConfig``, ``DemoConfig``, policy config and
    :class:`SFTConfig`: demonstrations -> a new policy with its processor fitted -> :func:`sft_train`
    (minibatches and noise drawn from a generator seeded by ``seed``). With ``init``, SFT
    fine-tunes that saved policy instead (e.g. a LeRobot SmolVLA folder). ``simulator``: the
    env's (default: the registered one). ``episodes``: the demonstrations, if already loaded
    (:func:`stepnft.data.demos.load_or_generate_demos`). The policy trains, and is returned, on
    ``device``, in ``precision`` and with ``gradient_checkpointing`` (:class:`Policy`'s memory settings)."""
    simulator = simulator or simulator_for(env_cfg)
    if episodes is None:
        episodes = load_or_generate_demos(demos_cfg, env_cfg, simulator, log)
    policy = load_policy(init) if init else make_policy(policy_cfg)
    data = sft_chunks(episodes, env_cfg, simulator, policy.config.horizon, demos_cfg.successful_only)
    instructions = [simulator.instruction(t) for t in simulator.validate_tasks(env_cfg.tasks)]
    fit_processor(policy, data, instructions, cache_dir, keep_statistics=init is not None)
    policy.to(device).set_precision(precision).set_gradient_checkpointing(gradient_checkpointing)
    with tqdm(total=sft_cfg.steps, desc="SFT", leave=False, mininterval=1.0) as bar:
        losses = sft_train(policy, data, sft_cfg, torch.Generator().manual_seed(seed),
                           on_step=lambda s, loss: (bar.update(1), bar.set_postfix(loss=f"{loss:.3f}", refresh=False)))
    if losses:
        log(f"SFT: {len(data['actions'])} chunks from {len(episodes)} demos, "
            f"loss {np.mean(losses[:50]):.3f} -> {np.mean(losses[-50:]):.3f}")
    bad = non_finite_samples(policy, probe_rows(data["obs"]))
    if bad:  # never saved: every later stage would act on NaN
        raise RunDiverged(f"the SFT policy samples non-finite actions ({', '.join(bad)}) on its demonstrations "
                          f"(sft.lr={sft_cfg.lr:g} too large?): it is not saved")
    return policy
