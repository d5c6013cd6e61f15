"""What every LeRobot flow VLA shares behind stepnft's :class:`~stepnft.policies.base.Policy`.

LeRobot's flow VLAs use stepnft's flow convention exactly: ``x_t = t ε + (1 - t) x0`` with
``t = 1`` pure noise, velocity target ``u = ε - x0``, and their sampler starts at ``t = 1`` and
steps ``x ← x + dt v`` with ``dt = -1/K``, which is stepnft's Euler step ``x_{t-d} = x_t - d v``
on the grid ``t_k = 1 - k/K``. So times and velocities pass through unchanged (no sign flip, no
``1 - t``), and the ODE sampler reproduces LeRobot's ``sample_actions`` on the same noise.

The chunk stepnft samples is the model's own: ``[chunk_size, max_action_dim]``, normalised and
padded like LeRobot's (the padded dimensions start as noise and evolve with the model's
velocity, as in ``sample_actions``; LeRobot's training loss covers them too, with target 0).
:meth:`env_actions` turns it into the robot's actions (the first ``action_dim`` dimensions,
un-normalised by LeRobot's post-processor); :meth:`model_actions` is the inverse for SFT targets.

Subclasses give the model's prefix (``encode``: images, instruction and, for SmolVLA, the state,
run once per call into the VLM's key/value cache), its denoising step against that cache
(``denoise``), which modules the prefix depends on, and LeRobot's own training flags.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib
import io
import json
import os
import shutil
from pathlib import Path
from typing import Any, Callable, ClassVar

import torch
from safetensors.torch import load_file, save, save_file
from torch import Tensor, nn

from stepnft.policies.base import CONFIG_NAME, Policy, non_finite, recompute
from stepnft.policies.lerobot import require_lerobot
from stepnft.policies.lerobot.configuration import LeRobotPolicyConfig
from stepnft.runs import write_atomic

require_lerobot()

from lerobot.configs.policies import PreTrainedConfig  # noqa: E402
from lerobot.utils.constants import OBS_STATE  # noqa: E402

from stepnft.policies.lerobot.processor import LeRobotProcessor  # noqa: E402

LEROBOT_DIR = "lerobot"
VLM_DIR = "vlm"
LORA_NAME = "lora.safetensors"
"""The LoRA adapters' weights of a policy with ``lora_rank > 0`` (``lerobot/`` then holds the base weights)."""
VALUE_CHUNK = 32
"""Calls per prefix pass of :meth:`LeRobotFlowPolicy.value_features`: PPO's pass over an
iteration's calls (hundreds) would otherwise hold the vision encoder's activations for all at once."""


@functools.lru_cache(maxsize=None)
def lerobot_version() -> tuple[int, ...]:
    """The installed LeRobot's version, as numbers (``(0, 6, 1)``)."""
    from importlib.metadata import version

    return tuple(int(part) for part in version("lerobot").split(".")[:3] if part.isdigit())


def lazy(target: str) -> Callable[[], Any]:
    """``module:name`` imported when first called (LeRobot's policy modules are heavy)."""
    module, name = target.split(":")
    return lambda: getattr(importlib.import_module(module), name)


def select_rows(tree: Any, rows: Tensor) -> Any:
    """Rows ``rows`` (dim 0) of every tensor in a tree of dicts, lists and tuples (a prefix's
    masks and key/value cache); anything else as it is."""
    if torch.is_tensor(tree):
        return tree.index_select(0, rows.to(tree.device))
    if isinstance(tree, dict):
        return {k: select_rows(v, rows) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return type(tree)(select_rows(v, rows) for v in tree)
    return tree


def cache_tensors(cache) -> list[tuple[Tensor, Tensor]]:
    """Every layer's ``(keys, values)`` of a transformers cache: its ``layers`` (transformers 5,
    LeRobot 0.6) or its legacy tuples (transformers 4)."""
    if hasattr(cache, "layers"):
        return [(layer.keys, layer.values) for layer in cache.layers]
    return list(cache.to_legacy_cache())


def cache_like(cache, tensors: list[tuple[Tensor, Tensor]]):
    """A new cache object of ``cache``'s class over ``tensors`` (per layer ``(keys, values)``): a
    denoising step may extend or crop it in place, never the prefix it was made from."""
    if not hasattr(cache, "layers"):
        return type(cache).from_legacy_cache(tuple(tensors))
    fresh = type(cache)()
    for index, (keys, values) in enumerate(tensors):
        fresh.update(keys, values, index)
    return fresh


def select_cache_rows(cache, rows: Tensor):
    """Rows ``rows`` of every layer of a transformers cache, in a new cache object."""
    return cache_like(cache, select_rows(cache_tensors(cache), rows))


_CHECKPOINTED: dict[tuple[type, tuple[str, ...]], type] = {}


def checkpoint_methods(module: nn.Module, names: tuple[str, ...], enabled: bool = True) -> None:
    """Make ``module``'s methods ``names`` recompute their activations in the backward pass
    (``torch.utils.checkpoint``) whenever gradients are on. The module's class is swapped for a
    subclass that overrides them (``enabled=False`` swaps it back), so the state dict is
    unchanged and a copy of the module (the EMA copy) is checkpointed alike."""
    plain = getattr(type(module), "_plain_class", type(module))
    if not enabled:
        module.__class__ = plain
        return

    def wrap(original):
        def method(self, *args, **kwargs):
            cache = kwargs.get("past_key_values")
            if not (torch.is_grad_enabled() and hasattr(cache, "layers")):
                return recompute(original, self, *args, **kwargs)
            # A transformers 5 cache (LeRobot 0.6) is extended in place by the layer: the backward
            # pass's recomputation runs on a copy of it as it was, so it neither sees its own
            # keys twice nor changes the cache again.
            # The layer's index in the cache: SmolVLA's attention methods take it (third argument);
            # a transformers decoder layer (π0's Gemma) knows it from its attention module.
            index = args[2] if len(args) > 2 else kwargs.get("layer_idx", None)
            if index is None:
                index = self.self_attn.layer_idx
            layer = cache.layers[index] if index < len(cache.layers) else None
            before = (layer.keys, layer.values) if layer is not None and layer.is_initialized else None
            calls = []

            def run(*a, **kw):
                if calls:
                    copy = type(cache)()
                    if before is not None:
                        copy.update(*before, index)
                    kw = kw | {"past_key_values": copy}
                calls.append(True)
                return original(self, *a, **kw)

            return recompute(run, *args, **kwargs)
        return method

    key = (plain, names)
    if key not in _CHECKPOINTED:
        _CHECKPOINTED[key] = type(f"Checkpointed{plain.__name__}", (plain,),
                                  {name: wrap(getattr(plain, name)) for name in names} | {"_plain_class": plain})
    module.__class__ = _CHECKPOINTED[key]


@contextlib.contextmanager
def quiet():
    """LeRobot and transformers print progress lines while building; keep stdout for stepnft."""
    with contextlib.redirect_stdout(io.StringIO()):
        yield


class LeRobotFlowPolicy(Policy):
    """A LeRobot flow VLA (``self.lerobot``) with LeRobot's pipelines as its processor."""

    config_class = LeRobotPolicyConfig
    # The prefix (vision encoder, VLM layers) dominates a velocity's cost: the update encodes it
    # once per policy call and shares it among the call's recorded steps (select_context).
    shares_prefix_in_update = True
    checkpoints_layers = True
    lerobot_class: ClassVar[Callable[[], type]]
    """The LeRobot policy class (imported on use)."""
    make_pipelines: ClassVar[Callable[[], Callable]]
    """LeRobot's ``make_*_pre_post_processors`` of the model (imported on use)."""

    def __init__(self, config: LeRobotPolicyConfig, lerobot_policy: nn.Module, processor: LeRobotProcessor):
        super().__init__(config)
        self.processor = processor
        self.lerobot = lerobot_policy
        self.lerobot.config.use_cache = True  # the adapter's denoising loop reads the prefix cache
        self.prefix_trainable = self.apply_train_scope()

    @staticmethod
    def make_processor(config) -> None:
        """Built from the LeRobot folder instead (:class:`LeRobotProcessor`)."""
        return None

    # --- what a LeRobot model implements ----------------------------------------------------------
    def prefix_modules(self) -> list[nn.Module]:
        """The modules the cached prefix depends on (frozen with ``train: expert``)."""
        raise NotImplementedError

    def set_lerobot_train_flags(self, scope: str) -> None:
        """Set LeRobot's own fine-tuning flags for ``scope`` and apply them (its set_requires_grad)."""
        raise NotImplementedError

    def prefix_hidden(self, obs: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        """The VLM's last-layer (normed) hidden states of the prefix ``[B, L, D]`` and its padding
        mask ``[B, L]``: the same pass as :meth:`encode`'s cache."""
        raise NotImplementedError

    def checkpointed_layers(self) -> list[tuple[nn.Module, tuple[str, ...]]]:
        """The modules and methods that gradient checkpointing recomputes, one transformer layer
        (or a part of one) per call: ``(module, method names)``."""
        raise NotImplementedError(f"gradient checkpointing is not implemented for {self.type}")

    def lora_targets(self) -> str:
        """The regular expression (over module names of ``self.lerobot``) of the VLM's linear
        layers that ``lora_rank`` puts adapters on."""
        raise NotImplementedError(f"LoRA is not implemented for {self.type}")

    def robot_actions(self, actions: Tensor) -> Tensor:
        """Model-specific output transform before un-normalisation (e.g. SmolVLA's Aloha adaptation)."""
        return actions

    def robot_actions_inverse(self, actions: Tensor) -> Tensor:
        return actions

    # --- trained parameters ---------------------------------------------------------------------
    def apply_train_scope(self) -> bool:
        """``requires_grad`` for ``config.train``; returns whether the prefix has trained parameters."""
        self.lerobot.requires_grad_(True)
        self.set_lerobot_train_flags(self.config.train)
        prefix = self.prefix_modules()
        if self.config.train == "expert":
            for module in prefix:
                module.requires_grad_(False)
        if self.config.lora_rank:
            self.add_lora()
        return any(p.requires_grad for m in prefix for p in m.parameters())

    def add_lora(self) -> None:
        """LoRA adapters (peft) of rank ``lora_rank`` on the VLM layers of :meth:`lora_targets`:
        the VLM backbone (the first of :meth:`prefix_modules`) freezes, and its adapters (``B``
        starts at 0: the function is unchanged) and the rest of the scope train. Saved apart, in
        ``lora.safetensors``."""
        try:
            from peft import LoraConfig, inject_adapter_in_model
        except ImportError as err:
            raise ValueError(f"policy lora_rank={self.config.lora_rank} needs peft: pip install peft "
                             f"({str(err).splitlines()[0]})") from None
        # The backbone (the first prefix module) freezes whole; peft freezes everything but its adapters, so
        # the rest of the scope (the action expert, SmolVLA's state projection) is trained again after it.
        backbone = {id(p) for p in self.prefix_modules()[0].parameters()}
        trained = {id(p) for p in self.lerobot.parameters() if p.requires_grad and id(p) not in backbone}
        with quiet():
            inject_adapter_in_model(LoraConfig(r=self.config.lora_rank, lora_alpha=self.config.lora_alpha,
                                               target_modules=self.lora_targets(), lora_dropout=0.0), self.lerobot)
        for name, param in self.lerobot.named_parameters():
            param.requires_grad_("lora_" in name or id(param) in trained)

    def lora_state_dict(self) -> dict[str, Tensor]:
        """The adapters' tensors (``self.lerobot``'s names)."""
        return {k: v for k, v in self.lerobot.state_dict().items() if "lora_" in k}

    @torch.no_grad()
    def merge_lora(self) -> "LeRobotFlowPolicy":
        """Fold the adapters into the weights they adapt (``W + (alpha / r) B A``) and remove them:
        the same model as a plain policy (``lora_rank`` 0), whose ``lerobot/`` folder LeRobot
        loads as the fine-tuned model. The VLM's layers then train whole if it trains on."""
        from peft.tuners.tuners_utils import BaseTunerLayer

        adapted = [(name, module) for name, module in self.lerobot.named_modules() if isinstance(module, BaseTunerLayer)]
        for name, module in adapted:
            module.merge()
            parent, _, child = name.rpartition(".")
            setattr(self.lerobot.get_submodule(parent) if parent else self.lerobot, child, module.get_base_layer())
        self.config = dataclasses.replace(self.config, lora_rank=0)
        self.prefix_trainable = self.apply_train_scope()
        return self

    # --- memory ----------------------------------------------------------------------------------
    def set_gradient_checkpointing(self, enabled: bool) -> "LeRobotFlowPolicy":
        """Per transformer layer (:meth:`checkpointed_layers`): the attention of every layer and
        its MLP recompute in backward, so an update keeps one layer's activations at a time."""
        for module, names in self.checkpointed_layers():
            checkpoint_methods(module, names, enabled)
        return super().set_gradient_checkpointing(enabled)

    # --- what a value head reads (PPO's critic) ---------------------------------------------------
    def value_features(self, obs: dict[str, Tensor]) -> Tensor:
        """``[B, D + S]``: the prefix's last-layer hidden states averaged over its valid tokens
        (images, instruction and, for SmolVLA, the state token; as πRL's value head on the VLM),
        then the normalised state ``[B, S]``. One prefix pass per call (in chunks of
        :data:`VALUE_CHUNK` calls), with gradients where the prefix trains (``train:
        expert+state`` / ``vlm``); with ``train: expert`` the features are constants."""
        calls = next(iter(obs.values())).shape[0]
        parts = []
        for start in range(0, calls, VALUE_CHUNK):
            part = {k: v[start:start + VALUE_CHUNK] for k, v in obs.items()}
            with torch.set_grad_enabled(torch.is_grad_enabled() and self.prefix_trainable):
                pooled = pool_prefix(*self.prefix_hidden(part))
            state = [part[OBS_STATE].flatten(1).to(pooled.dtype)] if OBS_STATE in part else []
            parts.append(torch.cat([pooled, *state], dim=1))
        return torch.cat(parts)

    # --- shapes and action spaces -----------------------------------------------------------------
    @property
    def chunk_shape(self) -> tuple[int, int]:
        """The model's chunk: ``(chunk_size, max_action_dim)`` (see the module doc)."""
        return self.lerobot.config.chunk_size, self.lerobot.config.max_action_dim

    def env_actions(self, chunk: Tensor) -> Tensor:
        """Model chunk ``[..., max_action_dim]`` -> robot actions ``[..., action_dim]`` (LeRobot's
        un-padding and post-processor)."""
        actions = self.robot_actions(chunk[..., : self.config.action_dim].clone())
        return self.processor.unnormalize_actions(actions)

    def model_actions(self, actions: Tensor) -> Tensor:
        """Robot actions ``[..., action_dim]`` -> the model's normalised, padded chunk (SFT targets)."""
        actions = self.robot_actions_inverse(self.processor.normalize_actions(actions).clone())
        padded = actions.new_zeros((*actions.shape[:-1], self.lerobot.config.max_action_dim))
        padded[..., : actions.shape[-1]] = actions
        return padded

    # --- save / load through LeRobot's own save_pretrained / from_pretrained ------------------------
    def save_pretrained(self, directory: str | Path) -> Path:
        """``config.json`` (stepnft's settings, ``"type"``), ``lerobot/`` (LeRobot's
        save_pretrained with its processor pipelines) and ``vlm/`` (a local VLM configuration)."""
        bad = non_finite(dict(self.state_dict()))
        if bad:
            raise ValueError(f"refusing to save a policy with non-finite values in {', '.join(bad[:3])}")
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        tmp = directory / f".{LEROBOT_DIR}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        with quiet():
            self.lerobot.save_pretrained(tmp)
        self.processor.save(tmp)
        if self.config.lora_rank:
            split_lora(tmp / "model.safetensors", directory / LORA_NAME)
        shutil.rmtree(directory / LEROBOT_DIR, ignore_errors=True)
        os.replace(tmp, directory / LEROBOT_DIR)
        vlm = Path(self.vlm_name())
        if vlm.is_dir() and vlm.resolve() != (directory / VLM_DIR).resolve():
            shutil.copytree(vlm, directory / VLM_DIR, dirs_exist_ok=True)
        settings = self.config.to_dict() | {"lerobot": LEROBOT_DIR}
        write_atomic(directory / CONFIG_NAME, json.dumps({"type": self.type, **settings}, indent=2))
        return directory

    def vlm_name(self) -> str:
        """The VLM / tokenizer the LeRobot config names (a hub id or a local folder)."""
        return self.lerobot.config.vlm_model_name

    @classmethod
    def read_config(cls, directory: Path) -> LeRobotPolicyConfig:
        return LeRobotPolicyConfig.read(directory)

    @classmethod
    def load_folder(cls, directory: Path, data: dict, map_location: str = "cpu") -> "LeRobotFlowPolicy":
        """A stepnft folder of this policy type, or a plain LeRobot folder (its own ``lerobot``)."""
        settings = LeRobotPolicyConfig.from_dict(data) if "lerobot" in data else LeRobotPolicyConfig(lerobot=".")
        lerobot_dir = directory / settings.lerobot
        if not (lerobot_dir / "model.safetensors").is_file():
            raise FileNotFoundError(f"no LeRobot policy at {lerobot_dir}: expected its config.json and model.safetensors")
        lerobot_cfg = PreTrainedConfig.from_pretrained(lerobot_dir)
        local_vlm = directory / VLM_DIR
        policy = cls.build(settings, lerobot_cfg, lerobot_dir, str(local_vlm) if local_vlm.is_dir() else None,
                           map_location)
        lora = directory / LORA_NAME
        if settings.lora_rank and lora.is_file():  # without the file: fresh adapters (B = 0, the same model)
            tensors, own = load_file(str(lora)), policy.lora_state_dict()
            wrong = sorted(set(own) ^ set(tensors)) or [k for k in own if own[k].shape != tensors[k].shape]
            if wrong:
                raise ValueError(f"{lora} does not match the policy's adapters (lora_rank {settings.lora_rank}): {wrong[0]}")
            policy.lerobot.load_state_dict(tensors, strict=False)
        bad = non_finite(dict(policy.state_dict()))
        if bad:
            raise ValueError(f"non-finite values in {', '.join(bad[:3])}")
        return policy

    @classmethod
    def build(cls, settings: LeRobotPolicyConfig, lerobot_cfg, lerobot_dir: Path | None, vlm: str | None,
              device: str = "cpu") -> "LeRobotFlowPolicy":
        """The policy from LeRobot's config: weights and pipelines from ``lerobot_dir`` (None: a
        new, randomly initialised model with fresh pipelines); ``vlm`` replaces the VLM folder
        the config names (a moved or copied policy folder carries its own)."""
        cls.prepare_lerobot_config(lerobot_cfg, vlm, device)
        policy_class = cls.lerobot_class()
        with quiet():
            if lerobot_dir is None:
                model = policy_class(lerobot_cfg)
            else:
                model = policy_class.from_pretrained(lerobot_dir, config=lerobot_cfg)
        processor = LeRobotProcessor.create(lerobot_cfg, cls.make_pipelines(), lerobot_dir,
                                            cls.processor_overrides(lerobot_cfg, device, vlm))
        settings = settings.completed(lerobot_config_dict(lerobot_cfg))
        return cls(settings, model, processor)

    @classmethod
    def prepare_lerobot_config(cls, lerobot_cfg, vlm: str | None, device: str) -> None:
        """Adjust LeRobot's config before building (the VLM folder, the device)."""
        lerobot_cfg.device = device

    @classmethod
    def processor_overrides(cls, lerobot_cfg, device: str, vlm: str | None = None) -> dict[str, Any]:
        """Overrides of the saved pipelines' steps (by LeRobot's step names); ``vlm`` as :meth:`build`'s."""
        return {"device_processor": {"device": device}}


def split_lora(weights: Path, lora: Path) -> None:
    """Split a LeRobot ``model.safetensors`` saved with LoRA adapters in place: the adapters'
    tensors go to ``lora``, the adapted layers' own weights get back their plain names
    (``q_proj.base_layer.weight`` -> ``q_proj.weight``), so LeRobot loads the folder as its model
    (the base weights; stepnft adds the adapters on top when it loads the policy folder)."""
    tensors = load_file(str(weights))
    adapters = {k: v for k, v in tensors.items() if "lora_" in k}
    base = {k.replace(".base_layer.", "."): v for k, v in tensors.items() if "lora_" not in k}
    write_atomic(lora, save(adapters))
    save_file(base, str(weights), metadata={"format": "pt"})


def pool_prefix(hidden: Tensor, pad_masks: Tensor) -> Tensor:
    """``[B, D]`` float32: hidden states ``[B, L, D]`` averaged over the valid tokens (``pad_masks`` ``[B, L]``)."""
    mask = pad_masks.to(torch.float32).unsqueeze(-1)
    return (hidden.float() * mask).sum(dim=1) / mask.sum(dim=1).clamp(min=1.0)


def lerobot_config_dict(lerobot_cfg) -> dict:
    """The fields of a LeRobot config that :meth:`LeRobotPolicyConfig.completed` reads."""
    features = {k: {"type": f.type.value, "shape": list(f.shape)}
                for k, f in {**lerobot_cfg.input_features, **lerobot_cfg.output_features}.items()}
    return {"input_features": features, "n_action_steps": lerobot_cfg.n_action_steps,
            "chunk_size": lerobot_cfg.chunk_size,
            "num_steps": getattr(lerobot_cfg, "num_steps", getattr(lerobot_cfg, "num_inference_steps", 10))}
