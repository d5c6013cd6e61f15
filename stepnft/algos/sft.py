"""Few-shot behaviour cloning: the flow-matching loss over demonstration chunks
(docs/algorithm.md §1), and the SFT stage of a run (demonstrations -> fitted policy)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Callable, ClassVar, Literal

import numpy as np
import torch
from tqdm.auto import tqdm

from stepnft.devices import to_device
from stepnft.losses import flow_matching_loss
from stepnft.policies.base import Policy, load_policy, make_policy
from stepnft.policies.vision import random_shift
from stepnft.sampling import flow_matching_pair, sample_flow_time
from stepnft.settings import Range, Settings


@dataclass
class SFTConfig(Settings):
    """Hyperparameters of flow-matching behaviour cloning."""

    section: ClassVar[str] = "sft"

    steps: Annotated[int, Range(ge=0)] = 3000
    """Gradient steps."""
    batch_size: Annotated[int, Range(ge=1)] = 256
    """Chunks per gradient step."""
    lr: Annotated[float, Range(gt=0)] = 3e-4
    """AdamW learning rate."""
    adam_betas: tuple[Annotated[float, Range(ge=0, lt=1)], Annotated[float, Range(ge=0, lt=1)]] = (0.9, 0.999)
    """AdamW (beta1, beta2)."""
    adam_eps: Annotated[float, Range(gt=0)] = 1e-8
    """AdamW epsilon."""
    weight_decay: Annotated[float, Range(ge=0)] = 1e-4
    """AdamW weight decay."""
    time_law: Literal["uniform", "beta"] = "uniform"
    """Law of the flow time t during training: ``uniform`` or ``beta`` (π0's)."""
    image_shift: Annotated[int, Range(ge=0)] = 4
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


def sft_from_demos(policy_cfg, sft_cfg: SFTConfig, demos_cfg, simulator, tasks: list[str], max_episode_steps: int,
                   seed: int, cache_dir: str | Path | None = None, log: Callable[[str], None] = print,
                   env_cfg=None, init: str | None = None, device: str = "cpu") -> Policy:
    """The SFT stage of a run: demonstrations (generated into ``demos_cfg.path`` if it holds
    none) -> chunks -> a new policy with its processor fitted -> :func:`sft_train`. ``env_cfg``
    (an ``EnvConfig``) gives the cameras to record and the state the policy sees. With ``init``,
    SFT fine-tunes that saved policy instead (e.g. a LeRobot SmolVLA folder); its processor
    keeps its statistics unless it has none. The policy trains, and is returned, on ``device``."""
    from stepnft.data.demos import demo_cameras, demos_to_chunks, generate_demos, load_demos

    path = Path(demos_cfg.path)
    cameras = list(env_cfg.cameras) if env_cfg is not None else []
    image_size = env_cfg.image_size if env_cfg is not None else 64
    state_obs = env_cfg.state_obs if env_cfg is not None else "full"
    # A simulator's own dataset (e.g. LIBERO's HDF5 files) is read at the env's cameras and size.
    own_dataset = not (path / "manifest.json").is_file() and simulator.has_dataset(path)
    if not (path / "manifest.json").is_file() and not own_dataset:
        count = max(demos_cfg.count(t) for t in tasks)
        log(f"generating {count} demonstrations per task into {path}")
        generate_demos(tasks, count, path, seed=demos_cfg.seed, action_noise=demos_cfg.action_noise,
                       max_episode_steps=max_episode_steps, simulator=simulator, max_attempts=demos_cfg.max_attempts,
                       successful_only=demos_cfg.successful_only, cameras=cameras, image_size=image_size)
    if cameras and not own_dataset and demo_cameras(path) != (cameras, image_size):
        recorded, size = demo_cameras(path)
        raise ValueError(f"demonstrations in {path} were recorded with cameras {recorded} at {size} px, the env "
                         f"renders {cameras} at {image_size} px: point --demos.path at a new folder to record them")
    keep = (lambda e: e.success) if demos_cfg.successful_only else (lambda e: True)  # noqa: E731
    episodes = [e for e in load_demos(path, simulator, cameras, image_size) if e.task in tasks and keep(e)]
    per_task = {t: [e for e in episodes if e.task == t][: demos_cfg.count(t)] for t in tasks}
    short = [t for t, eps in per_task.items() if len(eps) < demos_cfg.count(t)]
    if short:
        raise ValueError(f"demonstrations in {path} have too few {'successful ' * demos_cfg.successful_only}episodes "
                         f"of {short}: run `stepnft demos --env.tasks ... --demos.episodes N --demos.path {path}` with a "
                         "larger N, or point --demos.path at a new folder")
    policy = load_policy(init) if init else make_policy(policy_cfg)
    data = demos_to_chunks([e for eps in per_task.values() for e in eps], tasks, policy.config.horizon,
                           only_successful=demos_cfg.successful_only,
                           state_fn=lambda states: simulator.policy_state(states, state_obs), images=bool(cameras))
    if init is None or getattr(policy.processor, "needs_fit", False):
        policy.processor.fit(data["obs"]["state"])
    policy.processor.bind_instructions([simulator.instruction(t) for t in tasks], cache_dir)
    policy.to(device)
    gen = torch.Generator().manual_seed(seed)
    bar = tqdm(total=sft_cfg.steps, desc="SFT", leave=False, mininterval=1.0)
    losses = sft_train(policy, data, sft_cfg, gen,
                       on_step=lambda s, loss: (bar.update(1), bar.set_postfix(loss=f"{loss:.3f}", refresh=False)))
    bar.close()
    if losses:
        log(f"SFT: {len(data['actions'])} chunks from {sum(len(v) for v in per_task.values())} demos, "
            f"loss {np.mean(losses[:50]):.3f} -> {np.mean(losses[-50:]):.3f}")
    return policy
