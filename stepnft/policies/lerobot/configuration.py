"""stepnft's settings of a LeRobot flow VLA, saved as ``config.json`` beside the LeRobot folder.

A stepnft policy folder of a LeRobot policy::

    config.json     {"type": "smolvla", "lerobot": "lerobot", "train": "expert", "n_exec": ..., ...}
    lerobot/        LeRobot's own save_pretrained: config.json, model.safetensors,
                    policy_preprocessor.json, policy_postprocessor.json (+ their statistics)
    vlm/            the VLM configuration and tokenizer, when they came from a local folder

A plain LeRobot policy folder (LeRobot's ``config.json`` with its ``"type": "smolvla"``) loads as
is: it is its own ``lerobot`` folder and gets the default settings below. Reading these settings
needs no LeRobot, so the training loop can size its environments before anything is built.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from stepnft.policies.configuration import PolicyConfig
from stepnft.settings import WIDTH_MAX

TRAIN_SCOPES = ("expert", "expert+state", "vlm")


@dataclass
class LeRobotPolicyConfig:
    """How stepnft runs and trains a LeRobot flow VLA."""

    lerobot: str = "lerobot"
    """The LeRobot policy folder (LeRobot's save_pretrained layout), relative to this folder or absolute."""
    train: Literal["expert", "expert+state", "vlm"] = "expert"
    """Trained parameters: ``expert`` (the action expert and its action/time projections; the
    vision-language prefix is frozen, so it is encoded once per call without gradients, in
    rollouts and in the update), ``expert+state`` (also SmolVLA's state projection, which sits in
    the prefix: LeRobot's default SmolVLA fine-tuning set; the prefix then carries gradients) or
    ``vlm`` (also the VLM's language layers, LeRobot's train_expert_only=False; the vision
    encoder stays frozen)."""
    lora_rank: int = 0
    """With ``train: vlm``: LoRA adapters of this rank (peft) on the attention projections of the
    VLM's language layers, the VLM itself frozen (the action expert, and SmolVLA's state
    projection, still train whole); 0: the VLM's language layers train whole. The adapters are
    saved in ``lora.safetensors``, ``lerobot/`` keeps the base weights."""
    lora_alpha: int = 16
    """LoRA's scale numerator: the adapters' update is scaled by ``lora_alpha / lora_rank``."""
    n_exec: int = 0
    """Actions of a chunk executed before the policy is called again (0: LeRobot's n_action_steps)."""
    num_inference_steps: int = 0
    """Denoising steps K of the samplers (0: LeRobot's num_steps / num_inference_steps)."""
    prefix_cache: bool = True
    """Encode the prefix once per policy call and denoise against its cached keys and values.
    False runs the whole model (vision, language, state and action expert: SmolVLA's training
    forward) at every denoising step: the same velocities, K times the prefix compute; for
    comparisons only."""
    state_dim: int = 0
    """State size the policy takes (recorded from the LeRobot config)."""
    action_dim: int = 0
    """Action size sent to the env (recorded from the LeRobot config)."""
    horizon: int = 0
    """Chunk length H (LeRobot's chunk_size, recorded)."""
    cameras: list[str] = field(default_factory=list)
    """The simulator cameras that feed the policy's image features, in their order (recorded
    from LeRobot's ``observation.images.<name>`` features; edit it when a checkpoint's feature
    names are not the simulator's camera names: views are fed in this order)."""

    def __post_init__(self) -> None:
        if self.train not in TRAIN_SCOPES:
            raise ValueError(f"policy train={self.train!r} is invalid: choose one of {', '.join(TRAIN_SCOPES)}")
        counts = ("lora_rank", "lora_alpha", "n_exec", "num_inference_steps", "state_dim", "action_dim", "horizon")
        for name in counts:  # a hand-edited config.json: bounded before anything is sized from it
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value > WIDTH_MAX:
                raise ValueError(f"policy {name}={value!r} is invalid: it must be an integer <= {WIDTH_MAX}")
        if self.lora_rank < 0 or self.lora_alpha <= 0:
            raise ValueError("policy lora_rank must be >= 0 and lora_alpha > 0")
        if self.lora_rank and self.train != "vlm":
            raise ValueError(f"policy lora_rank={self.lora_rank} adapts the VLM's layers: it needs train=vlm "
                             f"(train={self.train!r} keeps them frozen)")
        if min(self.n_exec, self.num_inference_steps, self.state_dim, self.action_dim, self.horizon) < 0:
            raise ValueError("policy n_exec, num_inference_steps, state_dim, action_dim and horizon must be >= 0")
        if self.horizon and self.n_exec > self.horizon:
            raise ValueError(f"policy n_exec ({self.n_exec}) must be <= the chunk size ({self.horizon})")

    # The JSON round trip of every policy config (unknown keys refused), shared; not a run section
    # (a LeRobot policy enters a run as a folder: --init).
    to_dict = PolicyConfig.to_dict
    from_dict = classmethod(PolicyConfig.from_dict.__func__)

    @classmethod
    def read(cls, directory: str | Path) -> "LeRobotPolicyConfig":
        """The settings of a stepnft policy folder, or the defaults of a plain LeRobot folder
        (completed from its config.json)."""
        directory = Path(directory)
        data = json.loads((directory / "config.json").read_text())
        data.pop("type", None)
        if "lerobot" not in data:
            return cls(lerobot=".").completed(data)
        settings = cls.from_dict(data)
        # Folders saved before `cameras` was recorded: complete it from LeRobot's own config.
        lerobot_json = directory / settings.lerobot / "config.json"
        return settings.completed(json.loads(lerobot_json.read_text())) if lerobot_json.is_file() else settings

    @property
    def lang_dim(self) -> int:
        """Non-zero: the policy reads the instruction (LeRobot's VLAs tokenise it themselves)."""
        return 1

    def completed(self, lerobot_config: dict) -> "LeRobotPolicyConfig":
        """These settings with every 0 filled from a LeRobot config (its config.json as a dict)."""
        features = {**lerobot_config.get("input_features", {}), **lerobot_config.get("output_features", {})}

        def size(key: str) -> int:
            shape = features.get(key, {}).get("shape", [0])
            return int(shape[0]) if shape else 0

        steps = lerobot_config.get("num_steps", lerobot_config.get("num_inference_steps", 10))
        # Image features are LeRobot's observation.images.<name> (VISUAL); <name> is taken as the camera's.
        cameras = [k.split(".", 2)[-1] for k, f in lerobot_config.get("input_features", {}).items()
                   if f.get("type") == "VISUAL" or k.startswith("observation.images.")]
        values = {"n_exec": lerobot_config.get("n_action_steps", 1), "num_inference_steps": steps,
                  "state_dim": size("observation.state"), "action_dim": size("action"),
                  "horizon": lerobot_config.get("chunk_size", 1), "cameras": cameras}
        data = self.to_dict()
        for key, value in values.items():
            data[key] = data[key] or (value if key == "cameras" else int(value))
        return type(self)(**data)
