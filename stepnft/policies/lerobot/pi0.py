"""π0 and π0.5 (LeRobot 0.4) behind stepnft's policy interface, the same shape as SmolVLA's.

LeRobot 0.4.4 builds π0 / π0.5 only on a patched transformers (its ``PI0Pytorch`` checks for
``transformers.models.siglip.check``), which the package registry does not carry: without it,
building one raises :class:`PiUnavailable`, one line saying what is missing. stepnft patches no
transformers internals. What is below follows LeRobot's ``sample_actions`` of each model and is
exercised only where that transformers is installed (docs/lerobot.md).

Their prefix cache is a transformers ``DynamicCache``, which a forward pass extends in place
(with stock transformers every denoising step appends its suffix to it); each step here gets a
fresh cache object over the prefix's key/value tensors, so every Flow-SDE step sees the prefix
as it was encoded. In π0 the state enters the action expert's suffix, so with ``train: expert``
its state projection is trained; in π0.5 the state is part of the instruction tokens.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from stepnft.policies.base import PolicyUnavailable
from stepnft.policies.lerobot.adapter import (LeRobotFlowPolicy, cache_like, cache_tensors, lazy, pool_prefix,
                                            select_cache_rows, select_rows)

from lerobot.policies.pi0.modeling_pi0 import make_att_2d_masks  # noqa: E402
from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS  # noqa: E402

MISSING_TRANSFORMERS = ("{name} in LeRobot 0.4.4 needs LeRobot's patched transformers (the module "
                        "transformers.models.siglip.check, installed from LeRobot's own source instructions, not from "
                        "the package registry); this environment has the registry's transformers {version}. SmolVLA "
                        "needs no patch (type smolvla)")


class PiUnavailable(PolicyUnavailable):
    """π0 / π0.5 cannot be built: the patched transformers is missing."""


def transformers_patched() -> bool:
    """Whether LeRobot's patched transformers (needed by π0 / π0.5) is installed."""
    try:
        from transformers.models.siglip import check
    except ImportError:
        return False
    return bool(check.check_whether_transformers_replace_is_installed_correctly())


@dataclass
class PiPrefix:
    """One policy call's prefix: padding mask ``[B, L]``, its DynamicCache and (π0) the state."""

    pad_masks: Tensor
    past_key_values: object
    state: Tensor | None = None
    pooled: Tensor | None = None
    """``[B, D]`` the prefix's hidden states averaged over its valid tokens (``value_features``)."""


def lerobot_entry_points(model: str, policy_class: str) -> tuple[staticmethod, staticmethod]:
    """``(lerobot_class, make_pipelines)`` of LeRobot's ``lerobot.policies.<model>`` package
    (``pi0``, ``pi05``: the same layout), imported on use."""
    package = f"lerobot.policies.{model}"
    return (staticmethod(lazy(f"{package}.modeling_{model}:{policy_class}")),
            staticmethod(lazy(f"{package}.processor_{model}:make_{model}_pre_post_processors")))


class PI0Adapter(LeRobotFlowPolicy):
    """LeRobot's π0 with stepnft owning the denoising loop."""

    type, label = "pi0", "π0"
    state_in_suffix = True
    lerobot_class, make_pipelines = lerobot_entry_points("pi0", "PI0Policy")

    @classmethod
    def build(cls, settings, lerobot_cfg, lerobot_dir, vlm, device="cpu"):
        if not transformers_patched():
            import transformers

            raise PiUnavailable(MISSING_TRANSFORMERS.format(name=cls.label, version=transformers.__version__))
        return super().build(settings, lerobot_cfg, lerobot_dir, vlm, device)

    @property
    def model(self) -> nn.Module:
        return self.lerobot.model

    def vlm_name(self) -> str:
        return ""  # the tokenizer is named in the processor pipelines; no local VLM folder to carry

    def prefix_modules(self) -> list[nn.Module]:
        return [self.model.paligemma_with_expert.paligemma]

    def set_lerobot_train_flags(self, scope: str) -> None:
        with_expert = self.model.paligemma_with_expert
        self.lerobot.config.train_expert_only = with_expert.train_expert_only = scope != "vlm"
        with_expert.freeze_vision_encoder = self.lerobot.config.freeze_vision_encoder
        with_expert._set_requires_grad()

    def set_gradient_checkpointing(self, enabled: bool) -> "PI0Adapter":
        """LeRobot's own per-layer checkpointing of π0 (its language model, vision tower and
        expert; active while the model is in training mode, as in the update)."""
        if enabled:
            self.model.gradient_checkpointing_enable()
        else:
            self.model.gradient_checkpointing_disable()
        self.gradient_checkpointing = bool(enabled)
        return self

    def _prefix_inputs(self, obs: dict[str, Tensor]) -> tuple:
        images, img_masks = self.lerobot._preprocess_images(obs)
        return images, img_masks, obs[OBS_LANGUAGE_TOKENS], obs[OBS_LANGUAGE_ATTENTION_MASK]

    def _run_prefix(self, obs: dict[str, Tensor]) -> tuple[Tensor, object, Tensor]:
        """The prefix through the VLM: padding mask ``[B, L]``, DynamicCache, last hidden states ``[B, L, D]``."""
        embs, pad_masks, att_masks = self.model.embed_prefix(*self._prefix_inputs(obs))
        masks_4d = self.model._prepare_attention_masks_4d(make_att_2d_masks(pad_masks, att_masks))
        self.model.paligemma_with_expert.paligemma.language_model.config._attn_implementation = "eager"
        (hidden, _), cache = self.model.paligemma_with_expert.forward(
            attention_mask=masks_4d, position_ids=torch.cumsum(pad_masks, dim=1) - 1, past_key_values=None,
            inputs_embeds=[embs, None], use_cache=True)
        return pad_masks, cache, hidden

    def encode(self, obs: dict[str, Tensor]) -> PiPrefix:
        """The model's prefix (images, instruction) run once into its DynamicCache."""
        with torch.set_grad_enabled(torch.is_grad_enabled() and self.prefix_trainable):
            pad_masks, cache, hidden = self._run_prefix(obs)
        state = self.lerobot.prepare_state(obs) if self.state_in_suffix else None
        return PiPrefix(pad_masks, cache, state, pool_prefix(hidden, pad_masks))

    def prefix_hidden(self, obs: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        pad_masks, _, hidden = self._run_prefix(obs)
        return hidden, pad_masks

    def select_context(self, context: PiPrefix, rows: Tensor) -> PiPrefix:
        """The prefix of calls ``rows``: rows of its mask, of its cache's key/value tensors (in a
        new cache object) and of the state."""
        return PiPrefix(select_rows(context.pad_masks, rows), select_cache_rows(context.past_key_values, rows),
                        select_rows(context.state, rows), pooled=select_rows(context.pooled, rows))

    def denoise(self, context: PiPrefix, x_t: Tensor, t: Tensor) -> Tensor:
        # A new cache object over the same prefix tensors: the step may extend it, not the prefix.
        cache = cache_like(context.past_key_values, cache_tensors(context.past_key_values))
        if self.state_in_suffix:
            return self.model.denoise_step(state=context.state, prefix_pad_masks=context.pad_masks,
                                           past_key_values=cache, x_t=x_t, timestep=t)
        return self.model.denoise_step(prefix_pad_masks=context.pad_masks, past_key_values=cache, x_t=x_t, timestep=t)


class PI05Adapter(PI0Adapter):
    """LeRobot's π0.5 (the state is part of the instruction tokens, not the suffix)."""

    type, label = "pi05", "π0.5"
    state_in_suffix = False
    lerobot_class, make_pipelines = lerobot_entry_points("pi05", "PI05Policy")
