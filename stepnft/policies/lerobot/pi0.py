"""π0 and π0.5 behind stepnft's policy interface, the same shape as SmolVLA's.

LeRobot 0.6 builds π0 / π0.5 on the registry's transformers (its own ``pi_gemma`` layers).
LeRobot 0.4.4 built them only on a patched transformers (its ``PI0Pytorch`` checks for
``transformers.models.siglip.check``), which the package registry does not carry: there,
building one raises :class:`PiUnavailable`, one line saying what is missing. What is below
follows LeRobot's ``sample_actions`` of each model.

Their prefix cache is a transformers ``DynamicCache``, which a forward pass extends in place:
each denoising step gets a new cache object over the prefix's key/value tensors (LeRobot 0.6's
own ``denoise_step`` clones it again), so every Flow-SDE step sees the prefix as it was encoded.
In π0 the state enters the action expert's suffix, so with ``train: expert`` its state
projection is trained; in π0.5 the state is part of the instruction tokens (LeRobot's
pre-processor discretises it into the prompt).

Gradient checkpointing is stepnft's own, per decoder layer (:meth:`PI0Adapter.checkpointed_layers`):
LeRobot's switches on transformers' layer checkpointing, which in training mode drops the
``past_key_values`` a layer is given, so the action expert's steps against the cached prefix
would silently see no prefix at all.

Tiny sizes (``stepnft_tiny_vlm`` / ``stepnft_tiny_expert``, :data:`TINY_GEMMA`) are stepnft's:
:func:`register_tiny_sizes` (run when this module is imported) teaches LeRobot's π0 / π0.5
builders those two names and a 2-layer vision tower for them, so LeRobot's own
``PI0Policy.from_pretrained`` loads a tiny folder in any process that imported this module.
The full sizes (``gemma_2b`` VLM, ``gemma_300m`` expert) are LeRobot's own and need nothing.
"""

from __future__ import annotations

import contextvars
import functools
import importlib
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from stepnft.policies.base import PolicyUnavailable
from stepnft.policies.lerobot.adapter import (LeRobotFlowPolicy, cache_like, cache_tensors, lazy, lerobot_version,
                                            pool_prefix, select_cache_rows, select_rows)

from lerobot.policies.pi0 import modeling_pi0  # noqa: E402
from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS  # noqa: E402

make_att_2d_masks = modeling_pi0.make_att_2d_masks


def prepare_attention_masks_4d(model: nn.Module, masks_2d: Tensor) -> Tensor:
    """LeRobot's 4-d attention mask of 2-d masks (0.6: a module function; 0.4: a model method)."""
    if hasattr(model, "_prepare_attention_masks_4d"):
        return model._prepare_attention_masks_4d(masks_2d)
    return modeling_pi0.prepare_attention_masks_4d(masks_2d)

MISSING_TRANSFORMERS = ("{name} in LeRobot 0.4.4 needs LeRobot's patched transformers (the module "
                        "transformers.models.siglip.check, installed from LeRobot's own source instructions, not from "
                        "the package registry); this environment has the registry's transformers {version}. LeRobot "
                        "0.6 builds it on the registry's transformers (bash scripts/bootstrap.sh --lerobot); SmolVLA "
                        "needs no patch (type smolvla)")

TINY_GEMMA = {
    "stepnft_tiny_vlm": dict(width=64, depth=2, mlp_dim=128, num_heads=2, num_kv_heads=1, head_dim=16),
    "stepnft_tiny_expert": dict(width=32, depth=2, mlp_dim=64, num_heads=2, num_kv_heads=1, head_dim=16),
}
"""stepnft's tiny Gemma sizes (VLM and action expert share depth, heads and head size, as
LeRobot's gemma_2b / gemma_300m do: the expert attends to the VLM's keys and values)."""
TINY_VISION = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2, patch_size=8)
"""The SigLIP vision tower of a tiny VLM (its projector maps to the VLM's width)."""
TINY_VOCAB = 512
"""The tiny VLM's vocabulary (the byte-level tokenizer of ``stepnft.policies.lerobot.tiny`` has 263 tokens)."""
_BUILDING_TINY = contextvars.ContextVar("stepnft_building_tiny_pi", default=False)


class PiUnavailable(PolicyUnavailable):
    """π0 / π0.5 cannot be built: LeRobot 0.4.4 without its patched transformers."""


def transformers_patched() -> bool:
    """Whether LeRobot's patched transformers (needed by π0 / π0.5 on LeRobot 0.4.4) is installed."""
    try:
        from transformers.models.siglip import check
    except ImportError:
        return False
    return bool(check.check_whether_transformers_replace_is_installed_correctly())


def needs_patched_transformers() -> bool:
    """Whether this LeRobot builds π0 / π0.5 only on a patched transformers (0.4.x) and it is missing."""
    return lerobot_version() < (0, 5) and not transformers_patched()


def register_tiny_sizes() -> None:
    """Teach LeRobot's π0 and π0.5 builders (``modeling_pi0`` / ``modeling_pi05``) the tiny
    variants of :data:`TINY_GEMMA`: their Gemma sizes, a :data:`TINY_VISION` vision tower and a
    :data:`TINY_VOCAB` vocabulary (VLM and expert); the config check admits their names. Standard variants are
    untouched. Idempotent; a no-op on LeRobot 0.4 (whose π0 needs the patched transformers)."""
    if lerobot_version() < (0, 5):
        return
    for model in ("pi0", "pi05"):
        modeling = importlib.import_module(f"lerobot.policies.{model}.modeling_{model}")
        config_class = getattr(importlib.import_module(f"lerobot.policies.{model}.configuration_{model}"),
                               "PI0Config" if model == "pi0" else "PI05Config")
        if getattr(modeling, "_stepnft_tiny_sizes", False):
            continue
        modeling.get_gemma_config = _tiny_gemma_config(modeling.get_gemma_config, modeling.GemmaConfig)
        modeling.PaliGemmaForConditionalGenerationWithPiGemma = _tiny_paligemma(
            modeling.PaliGemmaForConditionalGenerationWithPiGemma)
        modeling.PiGemmaForCausalLM = _tiny_expert(modeling.PiGemmaForCausalLM)
        with_expert = modeling.PaliGemmaWithExpertModel
        with_expert.__init__ = _tiny_with_expert_init(with_expert.__init__)
        config_class.__post_init__ = _tiny_config_check(config_class.__post_init__)
        modeling._stepnft_tiny_sizes = True


def _tiny_gemma_config(original, gemma_config):
    @functools.wraps(original)
    def get_gemma_config(variant: str):
        if variant not in TINY_GEMMA:
            return original(variant)
        config = gemma_config(**TINY_GEMMA[variant])
        config.stepnft_tiny = True
        return config
    return get_gemma_config


def _tiny_with_expert_init(original):
    @functools.wraps(original)
    def __init__(self, vlm_config, action_expert_config, *args, **kwargs):
        token = _BUILDING_TINY.set(getattr(vlm_config, "stepnft_tiny", False))
        try:
            original(self, vlm_config, action_expert_config, *args, **kwargs)
        finally:
            _BUILDING_TINY.reset(token)
    return __init__


def _tiny_paligemma(original):
    def build(config):
        if _BUILDING_TINY.get():  # the VLM of a tiny variant: a tiny vision tower and vocabulary
            for key, value in TINY_VISION.items():
                setattr(config.vision_config, key, value)
            config.vision_config.projection_dim = config.text_config.hidden_size
            config.text_config.vocab_size = config._vocab_size = TINY_VOCAB
            config.image_token_index = TINY_VOCAB - 1
        return original(config=config)
    return build


def _tiny_expert(original):
    def build(config):
        if _BUILDING_TINY.get():  # its (unused) language-model head over a tiny vocabulary too
            config.vocab_size = TINY_VOCAB
        return original(config=config)
    return build


def _tiny_config_check(original):
    @functools.wraps(original)
    def __post_init__(self):
        names = (self.paligemma_variant, self.action_expert_variant)
        # LeRobot checks the variant names against its two; the tiny ones stand in as those.
        self.paligemma_variant = "gemma_2b" if names[0] in TINY_GEMMA else names[0]
        self.action_expert_variant = "gemma_300m" if names[1] in TINY_GEMMA else names[1]
        try:
            original(self)
        finally:
            self.paligemma_variant, self.action_expert_variant = names
    return __post_init__


register_tiny_sizes()


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
        if needs_patched_transformers():
            import transformers

            raise PiUnavailable(MISSING_TRANSFORMERS.format(name=cls.label, version=transformers.__version__))
        return super().build(settings, lerobot_cfg, lerobot_dir, vlm, device)

    def __init__(self, config, lerobot_policy, processor):
        if not config.prefix_cache:
            raise ValueError(f"policy prefix_cache=false is SmolVLA's joint pass; {self.label} always runs its "
                             "prefix once per call into its cache: remove prefix_cache from the policy's config.json")
        super().__init__(config, lerobot_policy, processor)

    @classmethod
    def processor_overrides(cls, lerobot_cfg, device: str, vlm: str | None = None) -> dict:
        """A folder's own tokenizer (``vlm/``, the tiny builds' offline one) replaces the one its
        pipeline names (LeRobot's default is PaliGemma's, from the hub)."""
        overrides = super().processor_overrides(lerobot_cfg, device, vlm)
        return overrides | ({"tokenizer_processor": {"tokenizer_name": vlm}} if vlm else {})

    @property
    def model(self) -> nn.Module:
        return self.lerobot.model

    @property
    def language_model(self) -> nn.Module:
        """The VLM's Gemma (``paligemma.model.language_model``; LeRobot 0.4: ``paligemma.language_model``)."""
        paligemma = self.model.paligemma_with_expert.paligemma
        return getattr(paligemma, "model", paligemma).language_model

    def vlm_name(self) -> str:
        """The tokenizer folder the pre-processor reads (a hub id for LeRobot's default)."""
        step = next((s for s in self.processor.pre.steps if hasattr(s, "tokenizer_name")), None)
        return getattr(step, "tokenizer_name", "") or ""

    def prefix_modules(self) -> list[nn.Module]:
        return [self.model.paligemma_with_expert.paligemma]

    def set_lerobot_train_flags(self, scope: str) -> None:
        with_expert = self.model.paligemma_with_expert
        self.lerobot.config.train_expert_only = with_expert.train_expert_only = scope != "vlm"
        with_expert.freeze_vision_encoder = self.lerobot.config.freeze_vision_encoder
        with_expert._set_requires_grad()
        # The expert's language-model head is never used (its outputs go through action_out_proj):
        # frozen, the EMA copy shares it and checkpoints leave it out (gemma_300m's is 263 M parameters).
        with_expert.gemma_expert.lm_head.requires_grad_(False)

    def checkpointed_layers(self) -> list[tuple[nn.Module, tuple[str, ...]]]:
        """Every decoder layer of the VLM's Gemma and of the action expert, and every layer of
        the vision tower (see the module doc for why not LeRobot's own)."""
        vision = self.model.paligemma_with_expert.paligemma
        vision = getattr(vision, "model", vision).vision_tower
        layers = [*self.language_model.layers, *self.model.paligemma_with_expert.gemma_expert.model.layers,
                  *vision.vision_model.encoder.layers]
        return [(layer, ("forward",)) for layer in layers]

    def lora_targets(self) -> str:
        """The attention projections (q, k, v, o) of the VLM's Gemma layers."""
        return r".*paligemma_with_expert\.paligemma\..*language_model\.layers\.\d+\.self_attn\.(q|k|v|o)_proj"

    def _embed_prefix(self, obs: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """The model's prefix embeddings, padding and attention masks of processed ``obs``
        (images through the vision tower, instruction tokens)."""
        images, img_masks = self.lerobot._preprocess_images(obs)
        return self.model.embed_prefix(images, img_masks, obs[OBS_LANGUAGE_TOKENS], obs[OBS_LANGUAGE_ATTENTION_MASK])

    def _run_prefix(self, obs: dict[str, Tensor]) -> tuple[Tensor, object, Tensor]:
        """The prefix through the VLM: padding mask ``[B, L]``, DynamicCache, last hidden states ``[B, L, D]``."""
        embs, pad_masks, att_masks = self._embed_prefix(obs)
        masks_4d = prepare_attention_masks_4d(self.model, make_att_2d_masks(pad_masks, att_masks))
        self.language_model.config._attn_implementation = "eager"  # as LeRobot's sample_actions
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
