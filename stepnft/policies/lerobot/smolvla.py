"""SmolVLA (LeRobot 0.4 and 0.6) behind stepnft's policy interface.

``encode`` runs SmolVLA's own ``embed_prefix`` (images, instruction tokens, state) and fills the
VLM's key/value cache (``fill_kv_cache=True``), once per policy call; ``denoise`` is SmolVLA's
``denoise_step(prefix_pad_masks, past_key_values, x_t, timestep)``, which only reads that cache
(``fill_kv_cache=False`` concatenates new tensors, the cache dict is left as it was), so every
Flow-SDE step sees the unmodified prefix. Times and velocities need no conversion (see
``stepnft.policies.lerobot.adapter``). The same VLM pass gives the last layer's hidden states of
the prefix, which PPO's value head reads pooled (``value_features``).

LeRobot 0.6 keeps the cache in a transformers ``DynamicCache`` instead of a dict (no
``fill_kv_cache``: a forward without a cache fills a new one); its ``denoise_step`` appends the
suffix in place and crops it off again. Each step here then gets a new cache object over the
prefix's tensors, so steps and rows never share one that a step changes.
"""

from __future__ import annotations

import functools
import inspect
from dataclasses import dataclass, replace

import torch
from torch import Tensor, nn

from stepnft.policies.lerobot.adapter import (LeRobotFlowPolicy, cache_like, cache_tensors, lazy, pool_prefix,
                                            select_cache_rows, select_rows)

from lerobot.policies.smolvla.modeling_smolvla import make_att_2d_masks  # noqa: E402
from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS, OBS_STATE  # noqa: E402


@functools.lru_cache(maxsize=None)
def _fills_on_request(model_class: type) -> bool:
    """Whether ``model_class.forward`` takes ``fill_kv_cache`` (read once per class: it is asked
    at every policy call and, without the prefix cache, every denoising step)."""
    return "fill_kv_cache" in inspect.signature(model_class.forward).parameters


@dataclass
class SmolVLAPrefix:
    """One policy call's prefix: its padding mask ``[B, L]`` and per-layer key/value cache; or,
    without the cache, the processed observations the whole model re-reads at every step."""

    pad_masks: Tensor | None = None
    past_key_values: object | None = None
    """LeRobot 0.4: a dict of per-layer tensors; 0.6: a transformers ``DynamicCache``."""
    obs: dict[str, Tensor] | None = None
    pooled: Tensor | None = None
    """``[B, D]`` the prefix's hidden states averaged over its valid tokens (the pooled part of
    ``value_features``), from the pass that filled the cache: a caller holding the context
    reads it without a second pass."""


class SmolVLAAdapter(LeRobotFlowPolicy):
    """LeRobot's SmolVLA with stepnft owning the denoising loop."""

    type = "smolvla"
    lerobot_class = staticmethod(lazy("lerobot.policies.smolvla.modeling_smolvla:SmolVLAPolicy"))
    make_pipelines = staticmethod(lazy("lerobot.policies.smolvla.processor_smolvla:make_smolvla_pre_post_processors"))

    @property
    def model(self) -> nn.Module:
        """SmolVLA's VLAFlowMatching."""
        return self.lerobot.model

    @property
    def _dict_cache(self) -> bool:
        """Whether this LeRobot keeps the prefix cache in a dict it fills on request (0.4:
        ``fill_kv_cache``) rather than in a ``DynamicCache`` (0.6)."""
        return _fills_on_request(type(self.model.vlm_with_expert))

    def prefix_modules(self) -> list[nn.Module]:
        return [self.model.vlm_with_expert.vlm, self.model.state_proj]

    def set_lerobot_train_flags(self, scope: str) -> None:
        cfg, vlm_with_expert = self.lerobot.config, self.model.vlm_with_expert
        cfg.train_expert_only = vlm_with_expert.train_expert_only = scope != "vlm"
        cfg.train_state_proj = scope != "expert"
        vlm_with_expert.freeze_vision_encoder = cfg.freeze_vision_encoder
        vlm_with_expert.set_requires_grad()
        self.model.set_requires_grad()

    def checkpointed_layers(self) -> list[tuple[nn.Module, tuple[str, ...]]]:
        """Every layer's attention (SmolVLA's own layer loop calls these two methods of
        ``vlm_with_expert``, VLM and expert together) and every language and expert layer's MLP."""
        with_expert = self.model.vlm_with_expert
        layers = [*with_expert.get_vlm_model().text_model.layers, *with_expert.lm_expert.layers]
        return [(with_expert, ("forward_attn_layer", "forward_cross_attn_layer")),
                *((layer.mlp, ("forward",)) for layer in layers)]

    def lora_targets(self) -> str:
        """The attention projections (q, k, v, o) of the VLM's language layers."""
        return r".*vlm_with_expert\.vlm\..*text_model\.layers\.\d+\.self_attn\.(q|k|v|o)_proj"

    def robot_actions(self, actions: Tensor) -> Tensor:
        return self.lerobot._pi_aloha_encode_actions(actions) if self.lerobot.config.adapt_to_pi_aloha else actions

    def robot_actions_inverse(self, actions: Tensor) -> Tensor:
        if self.lerobot.config.adapt_to_pi_aloha:
            return self.lerobot._pi_aloha_encode_actions_inv(actions)
        return actions

    @classmethod
    def prepare_lerobot_config(cls, lerobot_cfg, vlm: str | None, device: str) -> None:
        super().prepare_lerobot_config(lerobot_cfg, vlm, device)
        if vlm is not None:
            lerobot_cfg.vlm_model_name = vlm
        # Every weight comes from the checkpoint: never fetch the VLM's pretrained weights first.
        lerobot_cfg.load_vlm_weights = False

    @classmethod
    def processor_overrides(cls, lerobot_cfg, device: str, vlm: str | None = None) -> dict:
        return super().processor_overrides(lerobot_cfg, device, vlm) | {
            "tokenizer_processor": {"tokenizer_name": lerobot_cfg.vlm_model_name}}

    # --- the prefix, once per policy call -----------------------------------------------------------
    def _embed_prefix(self, obs: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """SmolVLA's prefix embeddings, padding and attention masks of processed ``obs``."""
        if self.lerobot.config.adapt_to_pi_aloha:
            obs = obs | {OBS_STATE: self.lerobot._pi_aloha_decode_state(obs[OBS_STATE].clone())}
        images, img_masks = self.lerobot.prepare_images(obs)
        return self.model.embed_prefix(images, img_masks, obs[OBS_LANGUAGE_TOKENS], obs[OBS_LANGUAGE_ATTENTION_MASK],
                                       state=self.lerobot.prepare_state(obs))

    def _run_prefix(self, obs: dict[str, Tensor]) -> tuple[Tensor, dict, Tensor]:
        """The prefix through the VLM: padding mask ``[B, L]``, key/value cache, and the last
        layer's hidden states ``[B, L, D]`` (computed by the same pass)."""
        embs, pad_masks, att_masks = self._embed_prefix(obs)
        fill = {"fill_kv_cache": True} if self._dict_cache else {}
        (hidden, _), past_key_values = self.model.vlm_with_expert.forward(
            attention_mask=make_att_2d_masks(pad_masks, att_masks), position_ids=torch.cumsum(pad_masks, dim=1) - 1,
            past_key_values=None, inputs_embeds=[embs, None], use_cache=True, **fill)
        return pad_masks, past_key_values, hidden

    def encode(self, obs: dict[str, Tensor]) -> SmolVLAPrefix:
        """SmolVLA's prefix of processed ``obs`` run into its key/value cache (no gradients unless
        prefix parameters are trained); without the cache, nothing is computed here."""
        if not self.config.prefix_cache:
            return SmolVLAPrefix(obs=obs)
        with torch.set_grad_enabled(torch.is_grad_enabled() and self.prefix_trainable):
            pad_masks, past_key_values, hidden = self._run_prefix(obs)
        return SmolVLAPrefix(pad_masks, past_key_values, pooled=pool_prefix(hidden, pad_masks))

    def prefix_hidden(self, obs: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        pad_masks, _, hidden = self._run_prefix(obs)
        return hidden, pad_masks

    def select_context(self, context: SmolVLAPrefix, rows: Tensor) -> SmolVLAPrefix:
        """The prefix of calls ``rows``: rows of its padding mask and of every layer's cached
        keys and values (without the cache: of the observations)."""
        cache = context.past_key_values
        cache = select_rows(cache, rows) if cache is None or isinstance(cache, dict) else select_cache_rows(cache, rows)
        return replace(context, pad_masks=select_rows(context.pad_masks, rows), past_key_values=cache,
                       obs=select_rows(context.obs, rows), pooled=select_rows(context.pooled, rows))

    # --- the action expert, once per denoising step ------------------------------------------------
    def denoise(self, context: SmolVLAPrefix, x_t: Tensor, t: Tensor) -> Tensor:
        """SmolVLA's ``denoise_step`` at ``x_t`` ``[B, chunk_size, max_action_dim]``, ``t`` ``[B]``."""
        if context.obs is None:
            cache = context.past_key_values
            if not isinstance(cache, dict):  # LeRobot 0.6's DynamicCache: a step extends the object it gets
                cache = cache_like(cache, cache_tensors(cache))
            return self.model.denoise_step(prefix_pad_masks=context.pad_masks, past_key_values=cache, x_t=x_t, timestep=t)
        return self._joint_velocity(context.obs, x_t, t)

    def _joint_velocity(self, obs: dict[str, Tensor], x_t: Tensor, t: Tensor) -> Tensor:
        """The whole model in one pass, vision included (SmolVLA's training forward): no cache."""
        with torch.set_grad_enabled(torch.is_grad_enabled() and self.prefix_trainable):
            prefix_embs, prefix_pad, prefix_att = self._embed_prefix(obs)
        suffix_embs, suffix_pad, suffix_att = self.model.embed_suffix(x_t, t)
        pad_masks = torch.cat([prefix_pad, suffix_pad], dim=1)
        att_masks = torch.cat([prefix_att, suffix_att], dim=1)
        (_, suffix_out), _ = self.model.vlm_with_expert.forward(
            attention_mask=make_att_2d_masks(pad_masks, att_masks), position_ids=torch.cumsum(pad_masks, dim=1) - 1,
            past_key_values=None, inputs_embeds=[prefix_embs, suffix_embs], use_cache=False,
            **({"fill_kv_cache": False} if self._dict_cache else {}))
        suffix_out = suffix_out[:, -self.lerobot.config.chunk_size:].to(dtype=torch.float32)
        return self.model.action_out_proj(suffix_out)
