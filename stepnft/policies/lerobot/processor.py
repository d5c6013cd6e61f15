"""Input and output processing of a LeRobot policy: stepnft's raw observations go through
LeRobot's own pre-processor, chunks through its post-processor.

Raw observations (``stepnft.batch``): ``state`` float32 [B, S], ``task`` int64 [B] (an index into
the bound instructions), optionally ``instruction`` int64 [B] (which variant of the task's
instruction) and ``image`` uint8 [B, V, 3, H, W] (V camera views). They become LeRobot's batch:
``observation.state``, one ``observation.images.*`` float image in [0, 1] per view (in the order of
the policy's image features) and ``task`` (the instruction strings). LeRobot's pipeline then
normalises the state, tokenises the instruction (SmolVLA: with a trailing newline) and, in the
post-processor, un-normalises the actions, exactly as ``lerobot-eval`` would.
"""

from __future__ import annotations

from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path

import torch
from torch import Tensor

from stepnft.policies.lerobot import require_lerobot

require_lerobot()

from lerobot.configs.types import FeatureType  # noqa: E402
from lerobot.processor import NormalizerProcessorStep, PolicyProcessorPipeline  # noqa: E402
from lerobot.processor.converters import (batch_to_transition, create_transition,  # noqa: E402
                                          policy_action_to_transition, transition_to_batch,
                                          transition_to_policy_action)
try:  # LeRobot 0.4: lerobot.processor.core; 0.6: lerobot.processor.pipeline (both export it here)
    from lerobot.processor import TransitionKey  # noqa: E402
except ImportError:  # pragma: no cover - a LeRobot 0.4 without the export
    from lerobot.processor.core import TransitionKey  # noqa: E402
from lerobot.processor.normalize_processor import hotswap_stats  # noqa: E402
from lerobot.utils.constants import (ACTION, OBS_STATE, POLICY_POSTPROCESSOR_DEFAULT_NAME,  # noqa: E402
                                     POLICY_PREPROCESSOR_DEFAULT_NAME)


@contextmanager
def local_tokenizer(folder: str | None):
    """Within the block, LeRobot's tokenizer step loads ``folder``'s tokenizer whatever name its
    pipeline factory gives it (π0's names PaliGemma's on the hub: nothing is downloaded here)."""
    if not folder:
        yield
        return
    from lerobot.processor import tokenizer_processor
    from transformers import AutoTokenizer

    class Local:
        @staticmethod
        def from_pretrained(*args, **kwargs):
            return AutoTokenizer.from_pretrained(folder)

    saved, tokenizer_processor.AutoTokenizer = tokenizer_processor.AutoTokenizer, Local
    try:
        yield
    finally:
        tokenizer_processor.AutoTokenizer = saved


class LeRobotProcessor:
    """A LeRobot policy's pre- and post-processor pipelines, fed from stepnft's raw observations."""

    def __init__(self, lerobot_config, pre: PolicyProcessorPipeline, post: PolicyProcessorPipeline,
                 state_min_std: float = 0.05):
        self.lerobot_config = lerobot_config
        self.pre, self.post = pre, post
        self.state_min_std = state_min_std
        self.image_keys = [k for k, f in lerobot_config.input_features.items() if f.type == FeatureType.VISUAL]
        self.state_dim = lerobot_config.input_features[OBS_STATE].shape[0]
        self.instruction_variants: list[list[str]] = []

    # --- building ------------------------------------------------------------------------
    @classmethod
    def create(cls, lerobot_config, make_pipelines, folder: Path | None = None,
               overrides: dict | None = None) -> "LeRobotProcessor":
        """The pipelines saved in the LeRobot ``folder`` (with ``overrides`` by step name), or new
        ones from ``make_pipelines(config)`` (LeRobot's ``make_*_pre_post_processors``, no
        statistics: identity normalisation until :meth:`fit`)."""
        name = f"{POLICY_PREPROCESSOR_DEFAULT_NAME}.json"
        if folder is not None and (folder / name).is_file():
            pre = PolicyProcessorPipeline.from_pretrained(folder, config_filename=name, overrides=overrides or {},
                                                          to_transition=batch_to_transition, to_output=transition_to_batch)
            post = PolicyProcessorPipeline.from_pretrained(
                folder, config_filename=f"{POLICY_POSTPROCESSOR_DEFAULT_NAME}.json",
                overrides={k: v for k, v in (overrides or {}).items() if k == "device_processor"},
                to_transition=policy_action_to_transition, to_output=transition_to_policy_action)
        else:
            tokenizer = (overrides or {}).get("tokenizer_processor", {}).get("tokenizer_name")
            with local_tokenizer(tokenizer):
                pre, post = make_pipelines(lerobot_config)
            for step in pre.steps:
                if tokenizer and getattr(step, "tokenizer_name", None):
                    step.tokenizer_name = tokenizer  # the saved pipeline names the folder it read
        return cls(lerobot_config, pre, post)

    def save(self, folder: Path) -> None:
        """Write both pipelines into the LeRobot ``folder`` (LeRobot's file names)."""
        self.pre.save_pretrained(folder)
        self.post.save_pretrained(folder)

    # --- statistics ------------------------------------------------------------------------
    @property
    def stats(self) -> dict:
        return next((s.stats for s in self.pre.steps if isinstance(s, NormalizerProcessorStep)), None) or {}

    @property
    def needs_fit(self) -> bool:
        """True while the state has no normalisation statistics (a new policy)."""
        return OBS_STATE not in self.stats

    @torch.no_grad()
    def fit(self, states: Tensor, actions: Tensor | None = None) -> None:
        """Normalisation statistics of the state ``[N, S]`` (and actions ``[N, ..., A]``) from
        demonstrations, as LeRobot computes a dataset's (mean, std, min, max, q01, q99). The state
        std is floored at ``state_min_std``: few demonstrations give tiny spreads."""
        stats = dict(self.stats)
        stats[OBS_STATE] = _feature_stats(states.float(), self.state_min_std)
        if actions is not None:
            stats[ACTION] = _feature_stats(actions.float().reshape(-1, actions.shape[-1]), 1e-3)
        self.pre, self.post = hotswap_stats(self.pre, stats), hotswap_stats(self.post, stats)

    # --- instructions ----------------------------------------------------------------------
    def bind_instructions(self, instructions: Sequence[str | Sequence[str]], cache_dir: str | Path | None = None) -> None:
        """The instructions raw ``task`` indices refer to; an entry may list the task's variants
        (raw ``instruction`` picks one, the first when absent). Tokenised per call by LeRobot's
        pipeline (``cache_dir`` is unused: nothing to cache)."""
        self.instruction_variants = [[item] if isinstance(item, str) else list(item) for item in instructions]

    @contextmanager
    def bound(self, instructions: Sequence[str | Sequence[str]], cache_dir: str | Path | None = None):
        """Within the block, bound to ``instructions`` (e.g. an evaluation suite's variants); restored after."""
        saved = self.instruction_variants
        try:
            self.bind_instructions(instructions, cache_dir)
            yield self
        finally:
            self.instruction_variants = saved

    @property
    def instructions(self) -> list[str]:
        return [v[0] for v in self.instruction_variants]

    def _texts(self, raw: dict[str, Tensor]) -> list[str]:
        if not self.instruction_variants:
            raise ValueError("this policy is conditioned on language: bind_instructions() before use")
        variant = raw.get("instruction", torch.zeros_like(raw["task"]))
        return [self.instruction_variants[int(k)][int(v)] for k, v in zip(raw["task"], variant)]

    # --- observations -> model inputs ------------------------------------------------------
    def lerobot_batch(self, raw: dict[str, Tensor]) -> dict:
        """Raw stepnft observations as LeRobot's batch (before its pre-processor)."""
        state = raw["state"].float()
        if state.shape[-1] != self.state_dim:
            raise ValueError(f"the policy takes {self.state_dim}-d states, the env gives {state.shape[-1]}-d ones: "
                             "use an env whose state matches the LeRobot policy's observation.state")
        batch = {OBS_STATE: state, "task": self._texts(raw)}
        if self.image_keys:
            if "image" not in raw:
                raise ValueError(f"this policy sees camera images ({', '.join(self.image_keys)}): the env must "
                                 "render them (an `image` observation)")
            images = raw["image"] if raw["image"].ndim == 5 else raw["image"][:, None]
            if images.shape[1] > len(self.image_keys):
                raise ValueError(f"the env renders {images.shape[1]} camera views, the policy takes "
                                 f"{len(self.image_keys)} ({', '.join(self.image_keys)})")
            scale = 255.0 if images.dtype == torch.uint8 else 1.0
            for i in range(images.shape[1]):
                batch[self.image_keys[i]] = images[:, i].float() / scale
        return batch

    def __call__(self, raw: dict[str, Tensor]) -> dict[str, Tensor]:
        """Model inputs: LeRobot's pre-processed observation tensors (state first)."""
        out = self.pre(self.lerobot_batch(raw))
        return {k: v for k, v in out.items() if k.startswith("observation.") and torch.is_tensor(v)}

    # --- actions -----------------------------------------------------------------------------
    def unnormalize_actions(self, actions: Tensor) -> Tensor:
        """LeRobot's post-processor: model actions ``[..., A]`` -> the robot's (CPU)."""
        return self.post(actions)

    def normalize_actions(self, actions: Tensor) -> Tensor:
        """The inverse: robot actions ``[..., A]`` -> the model's normalised ones (SFT targets)."""
        transition = create_transition(action=actions.float())
        for step in self.pre.steps:
            if isinstance(step, NormalizerProcessorStep):
                transition = step(transition)
        return transition[TransitionKey.ACTION]


def _feature_stats(x: Tensor, min_std: float) -> dict[str, list[float]]:
    """LeRobot's statistics of a feature ``[N, D]`` (lists: JSON-safe for its pipeline configs)."""
    q = torch.quantile(x, torch.tensor([0.01, 0.99]), dim=0)
    return {"mean": x.mean(0).tolist(), "std": x.std(0).clamp(min=min_std).tolist(), "min": x.min(0).values.tolist(),
            "max": x.max(0).values.tolist(), "q01": q[0].tolist(), "q99": q[1].tolist()}
