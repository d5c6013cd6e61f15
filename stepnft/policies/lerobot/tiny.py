"""Offline LeRobot VLAs (SmolVLA, π0, π0.5): configuration folders written by the project (no
download), and new, randomly initialised policy folders built on them.

SmolVLA reads its VLM from ``SmolVLAConfig.vlm_model_name``: a ``SmolVLMConfig`` ``config.json``,
a tokenizer carrying the image special tokens SmolVLA looks up (``<fake_token_around_image>``,
``<global-img>``) and the image / video processor configurations. With
``load_vlm_weights=False`` SmolVLA builds the VLM from that configuration, randomly
initialised, so :func:`write_vlm` makes tests and CPU runs independent of the network:

- ``tiny``: a 4-layer, 64-wide language model and a 2-layer vision encoder on 64 px images
  (a few hundred thousand parameters; builds in a fraction of a second);
- ``smolvla``: the architecture of SmolVLA's backbone, SmolVLM2-500M (16 of its 32 language
  layers kept, 512 px images), randomly initialised: about 450 M parameters, for throughput.

The tokenizer is byte-level BPE without merges (256 byte symbols plus the special tokens), built
with ``tokenizers``: any instruction tokenises, one token per byte.

π0 and π0.5 (LeRobot 0.6) take their sizes from LeRobot's Gemma variants: ``full`` is theirs
(a PaliGemma with the ``gemma_2b`` language model and SigLIP-So400m vision tower, a
``gemma_300m`` action expert: about 3.5 B parameters), ``tiny`` is stepnft's
``stepnft_tiny_vlm`` / ``stepnft_tiny_expert`` (2 layers, 64 / 32 wide, a 2-layer 32-wide vision
tower on 32 px images; ``stepnft.policies.lerobot.pi0``). Their tokenizer is the same byte-level
one, saved in the policy's ``vlm/`` folder (LeRobot's default names PaliGemma's on the hub).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from stepnft.policies.lerobot import require_lerobot

require_lerobot()

SMOLVLM_TOKENS = {"fake_image_token": "<fake_token_around_image>", "image_token": "<image>",
                  "end_of_utterance_token": "<end_of_utterance>", "global_image_token": "<global-img>"}

SIZES = {
    "tiny": dict(text=dict(hidden_size=64, intermediate_size=128, num_hidden_layers=4, num_attention_heads=4,
                           num_key_value_heads=2, head_dim=16),
                 vision=dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2,
                             image_size=64, patch_size=8),
                 scale_factor=2, vocab_size=None, vlm_layers=4),
    "smolvla": dict(text=dict(hidden_size=960, intermediate_size=2560, num_hidden_layers=32, num_attention_heads=15,
                              num_key_value_heads=5, head_dim=64, rope_theta=100000.0),
                    vision=dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
                                image_size=512, patch_size=16),
                    scale_factor=4, vocab_size=49280, vlm_layers=16),
}
"""VLM sizes: ``vlm_layers`` is SmolVLA's ``num_vlm_layers`` (language layers kept)."""


def byte_tokenizer():
    """A byte-level BPE tokenizer (no merges) with SmolVLM's special tokens, as a transformers tokenizer."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast

    alphabet = sorted(pre_tokenizers.ByteLevel.alphabet())
    tokenizer = Tokenizer(models.BPE(vocab={c: i for i, c in enumerate(alphabet)}, merges=[]))
    tokenizer.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tokenizer.decoder = decoders.ByteLevel()
    tokenizer.add_special_tokens(["<|im_start|>", "<|im_end|>", "<video>", *SMOLVLM_TOKENS.values()])
    return PreTrainedTokenizerFast(tokenizer_object=tokenizer, bos_token="<|im_start|>", eos_token="<end_of_utterance>",
                                   pad_token="<|im_end|>", extra_special_tokens=SMOLVLM_TOKENS,
                                   model_input_names=["input_ids", "attention_mask"])


def write_vlm(folder: str | Path, size: Literal["tiny", "smolvla"] = "tiny") -> Path:
    """Write a SmolVLM configuration, tokenizer and image/video processor configs to ``folder``."""
    from transformers import SmolVLMConfig, SmolVLMImageProcessor, SmolVLMProcessor
    from transformers.models.smolvlm.video_processing_smolvlm import SmolVLMVideoProcessor

    if size not in SIZES:
        raise ValueError(f"unknown VLM size {size!r}; choose one of {', '.join(SIZES)}")
    spec, folder = SIZES[size], Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    tokenizer = byte_tokenizer()
    vision = spec["vision"]
    config = SmolVLMConfig(
        text_config=dict(model_type="llama", vocab_size=spec["vocab_size"] or len(tokenizer), rms_norm_eps=1e-5,
                         max_position_embeddings=8192, pad_token_id=tokenizer.pad_token_id, tie_word_embeddings=False,
                         **spec["text"]),
        vision_config=vision, scale_factor=spec["scale_factor"],
        image_token_id=tokenizer.convert_tokens_to_ids(SMOLVLM_TOKENS["image_token"]), pad_token_id=tokenizer.pad_token_id)
    config.save_pretrained(folder)
    edge = {"longest_edge": vision["image_size"]}
    image_seq_len = (vision["image_size"] // vision["patch_size"]) ** 2 // spec["scale_factor"] ** 2
    SmolVLMProcessor(image_processor=SmolVLMImageProcessor(do_image_splitting=False, max_image_size=edge, size=edge),
                     tokenizer=tokenizer, video_processor=SmolVLMVideoProcessor(max_image_size=edge, size=edge),
                     image_seq_len=image_seq_len).save_pretrained(folder)
    return folder


MODELS = ("smolvla", "pi0", "pi05")
"""The LeRobot models :func:`new_vla` builds."""
PI_SIZES = {"tiny": ("stepnft_tiny_vlm", "stepnft_tiny_expert", 32), "full": ("gemma_2b", "gemma_300m", 224)}
"""π0 / π0.5 sizes: (VLM variant, action expert variant, image side)."""


@dataclass
class NewVLA:
    """Write a new, randomly initialised LeRobot VLA policy folder (stepnft's layout: config.json +
    lerobot/ + vlm/) built on an offline configuration: the start of `stepnft sft --init`."""

    out: str
    """Policy folder to create (must not exist)."""
    model: Literal["smolvla", "pi0", "pi05"] = "smolvla"
    """LeRobot model: smolvla, pi0 or pi05 (π0 / π0.5 need LeRobot 0.6)."""
    size: Literal["tiny", "full", "smolvla"] = "tiny"
    """tiny (tests, CPU learning runs) or full (the model's real architecture, random weights:
    SmolVLA ~450 M parameters, π0 / π0.5 ~3.5 B); smolvla is SmolVLA's full size by its old name."""
    state_dim: int = 39
    """State size (MetaWorld: 39)."""
    action_dim: int = 4
    """Action size (MetaWorld: 4)."""
    chunk_size: int = 4
    """Actions per chunk (SmolVLA's chunk_size; stepnft's horizon)."""
    n_exec: int = 4
    """Actions executed per policy call (SmolVLA's n_action_steps)."""
    num_steps: int = 4
    """Denoising steps K."""
    cameras: list[str] = field(default_factory=lambda: ["corner"])
    """Camera views, in the order the env renders them (image features observation.images.<name>)."""
    image_size: int = 64
    """Side of the square camera images the env renders."""
    train: Literal["expert", "expert+state", "vlm"] = "expert"
    """Trained parameters (see stepnft.policies.lerobot.configuration)."""
    lora_rank: int = 0
    """With --train vlm: LoRA adapters of this rank on the VLM's language layers instead of
    training them whole (needs peft); 0: none."""
    seed: int = 0
    """Seed of the random initialisation."""


NewSmolVLA = NewVLA
"""The name :class:`NewVLA` had when it built SmolVLA only (``model`` defaults to smolvla)."""


def build_smolvla(spec: NewVLA, vlm_dir: str | Path):
    """A new, randomly initialised SmolVLA adapter as ``spec`` describes, its VLM configuration
    written to ``vlm_dir`` (not saved: see :func:`new_smolvla`)."""
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig

    from stepnft.policies.lerobot.configuration import LeRobotPolicyConfig
    from stepnft.policies.lerobot.smolvla import SmolVLAAdapter

    if spec.model != "smolvla":
        return build_pi(spec, vlm_dir)
    size = "smolvla" if spec.size == "full" else spec.size
    spec = replace(spec, size=size)
    vlm = write_vlm(vlm_dir, spec.size)
    side = SIZES[spec.size]["vision"]["image_size"]
    pad = 32 if spec.size == "smolvla" else 0  # SmolVLA pads state and action to 32; the tiny model does not pad
    features = {"observation.state": PolicyFeature(FeatureType.STATE, (spec.state_dim,))}
    features |= {f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, spec.image_size, spec.image_size))
                 for c in spec.cameras}
    lerobot_cfg = SmolVLAConfig(
        vlm_model_name=str(vlm.resolve()), load_vlm_weights=False, num_vlm_layers=SIZES[spec.size]["vlm_layers"],
        chunk_size=spec.chunk_size, n_action_steps=spec.n_exec, num_steps=spec.num_steps,
        max_state_dim=max(pad, spec.state_dim), max_action_dim=max(pad, spec.action_dim),
        resize_imgs_with_padding=(side, side), input_features=features,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (spec.action_dim,))}, device="cpu")
    torch.manual_seed(spec.seed)
    return SmolVLAAdapter.build(LeRobotPolicyConfig(train=spec.train, lora_rank=spec.lora_rank), lerobot_cfg,
                                None, None)


def build_pi(spec: NewVLA, vlm_dir: str | Path, dtype: str = "float32"):
    """A new, randomly initialised π0 / π0.5 adapter as ``spec`` describes (LeRobot 0.6), its
    tokenizer written to ``vlm_dir`` (not saved: see :func:`new_vla`). ``dtype`` is LeRobot's
    build precision: ``bfloat16`` casts the model (but its vision tower and norms) to bfloat16
    instead of float32, so a full-size build never holds the 14 GB float32 copy (the cost
    benchmark's bf16 rows); the trained parameters are then bfloat16 too, until cast back."""
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature

    from stepnft.policies.lerobot.configuration import LeRobotPolicyConfig
    from stepnft.policies.lerobot.pi0 import PI0Adapter, PI05Adapter, PiUnavailable, needs_patched_transformers

    if needs_patched_transformers():
        raise PiUnavailable(f"{spec.model} needs LeRobot 0.6 (bash scripts/bootstrap.sh --lerobot): this LeRobot "
                            "builds it only on its patched transformers")
    size = "full" if spec.size == "smolvla" else spec.size
    vlm_variant, expert_variant, side = PI_SIZES[size]
    vlm_dir = Path(vlm_dir)
    vlm_dir.mkdir(parents=True, exist_ok=True)
    byte_tokenizer().save_pretrained(vlm_dir)
    features = {"observation.state": PolicyFeature(FeatureType.STATE, (spec.state_dim,))}
    features |= {f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, spec.image_size, spec.image_size))
                 for c in spec.cameras}
    if spec.model == "pi0":
        from lerobot.policies.pi0.configuration_pi0 import PI0Config as config_class
        adapter, prompt = PI0Adapter, 48
    else:
        from lerobot.policies.pi05.configuration_pi05 import PI05Config as config_class
        # π0.5's prompt carries the discretised state: one byte token per character of it.
        adapter, prompt = PI05Adapter, 64 + 4 * spec.state_dim
    pad = 32 if size == "full" else 0  # LeRobot pads state and action to 32; the tiny model does not pad
    lerobot_cfg = config_class(
        paligemma_variant=vlm_variant, action_expert_variant=expert_variant, dtype=dtype,
        chunk_size=spec.chunk_size, n_action_steps=spec.n_exec, num_inference_steps=spec.num_steps,
        max_state_dim=max(pad, spec.state_dim), max_action_dim=max(pad, spec.action_dim),
        image_resolution=(side, side), tokenizer_max_length=prompt, input_features=features,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (spec.action_dim,))}, device="cpu")
    torch.manual_seed(spec.seed)
    return adapter.build(LeRobotPolicyConfig(train=spec.train, lora_rank=spec.lora_rank), lerobot_cfg, None,
                         str(vlm_dir.resolve()))


def build_vla(spec: NewVLA, vlm_dir: str | Path, dtype: str = "float32"):
    """A new, randomly initialised adapter of ``spec.model`` (not saved: see :func:`new_vla`);
    ``dtype`` as :func:`build_pi`'s (SmolVLA is built in float32)."""
    if spec.model not in MODELS:
        raise ValueError(f"unknown LeRobot model {spec.model!r}; choose one of {', '.join(MODELS)}")
    return build_pi(spec, vlm_dir, dtype) if spec.model != "smolvla" else build_smolvla(spec, vlm_dir)


def new_vla(spec: NewVLA):
    """Build and save the policy :class:`NewVLA` describes (its VLM configuration or tokenizer
    in ``out/vlm``); returns it."""
    out = Path(spec.out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"{out} is not empty: choose a new folder for the policy")
    policy = build_vla(spec, out / "vlm")
    policy.save_pretrained(out)
    return policy


new_smolvla = new_vla
"""The name :func:`new_vla` had when it built SmolVLA only."""
