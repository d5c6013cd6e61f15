"""The policy interface and the registry keyed by the saved ``type`` (LeRobot-style).

A policy is a velocity field ``v_θ(x_t, t | o)`` over action chunks ``[H, A]``. It splits into
``encode(obs)`` (the observation context, computed once per policy call: for a VLA the
vision-language prefix) and ``denoise(context, x_t, t)`` (the action expert), so sampling runs
the encoder once and the denoiser K times. ``obs`` is the *processed* observation dict: raw
observations go through ``policy.processor`` first (normalisation, instruction lookup), outside
the network. ``value_features(obs)`` gives the flat features a value head reads (PPO's critic):
by default the encoder's output; a VLA, whose context is a key/value cache, gives its own.

Saved as ``config.json`` (with ``"type"``) + ``model.safetensors`` + ``processor.safetensors``;
loading dispatches on ``type`` and never unpickles. A policy saved in another layout (a LeRobot
policy: ``stepnft.policies.lerobot``) overrides ``load_folder`` / ``save_pretrained``; one whose
chunks live in another space than the env's actions (normalised, padded) overrides
``env_actions`` / ``model_actions``.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import warnings
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from stepnft.devices import bf16_capped_note, to_device
from stepnft.plugins import PluginRegistry
from stepnft.policies.configuration import PolicyConfig, missing_run_fields
from stepnft.runs import write_atomic
from stepnft.sampling import ChunkSample, sample_chunk
from stepnft.settings import read_settings_text

CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"
PROCESSOR_NAME = "processor.safetensors"

POLICY_TYPES: dict[str, str] = PluginRegistry("stepnft.policies", {
    "flow": "stepnft.policies.flow:FlowPolicy",
    "smolvla": "stepnft.policies.lerobot.smolvla:SmolVLAAdapter",
    "pi0": "stepnft.policies.lerobot.pi0:PI0Adapter",
    "pi05": "stepnft.policies.lerobot.pi0:PI05Adapter",
})
"""Registered policy classes by saved ``type`` (imported on first use): stepnft's own and those
of installed packages (entry-point group ``stepnft.policies``, ``stepnft.plugins``)."""


def non_finite(tensors: dict[str, Tensor]) -> list[str]:
    """Names of the floating-point tensors holding NaN or infinity."""
    return [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]


PRECISIONS = ("fp32", "bf16")
"""How a policy computes (``--precision``): ``fp32`` everywhere, or ``bf16``: frozen parameters
stored in bfloat16 and the forward passes under autocast (:meth:`Policy.set_precision`)."""


def recompute(fn, *args, **kwargs):
    """``fn(*args, **kwargs)``; while gradients are on, its activations are recomputed in the
    backward pass instead of kept (``torch.utils.checkpoint``, non-reentrant)."""
    if torch.is_grad_enabled():
        return checkpoint(fn, *args, use_reentrant=False, **kwargs)
    return fn(*args, **kwargs)


PROBE_ROWS = 8
"""Observations a saved policy is checked on (:func:`non_finite_samples`)."""


def probe_rows(obs: dict[str, Tensor], rows: int = PROBE_ROWS) -> dict[str, Tensor]:
    """At most ``rows`` raw observations spread evenly over ``obs`` (``[N, ...]`` per key), e.g.
    over a rollout batch's calls or the demonstrations' steps, kept on the CPU."""
    n = next(iter(obs.values())).shape[0]
    idx = torch.linspace(0, n - 1, min(rows, n)).round().long()
    return {k: v[idx].cpu() for k, v in obs.items()}


@torch.no_grad()
def non_finite_samples(policy: "Policy", raw_obs: dict[str, Tensor], noise_level: float = 0.5) -> list[str]:
    """The samplers (``ODE``, ``Flow-SDE`` at ``noise_level``) whose env actions for the raw
    observations ``raw_obs`` (``[B, ...]``, e.g. :func:`probe_rows`) are not all finite: a policy
    with finite weights may still overflow while sampling. Draws its noise from its own
    generator and leaves every module's train/eval mode as it was, so no random stream or
    result of the caller changes. ``policy.processor`` must be bound (as for sampling)."""
    modes = [(m, m.training) for m in policy.modules()]
    policy.eval()
    try:
        obs = policy.prepare(raw_obs)
        bad = []
        for name, level in (("ODE", 0.0), ("Flow-SDE", noise_level)):
            chunk = policy.sample(obs, noise_level=level, generator=torch.Generator().manual_seed(0)).actions
            if not bool(torch.isfinite(policy.env_actions(chunk.cpu())).all()):
                bad.append(name)
        return bad
    finally:
        for module, training in modes:
            module.training = training


class PolicyUnavailable(ValueError):
    """A registered policy type whose optional extra (e.g. LeRobot) is not installed here."""


def policy_class(type_name: str) -> type["Policy"]:
    if type_name not in POLICY_TYPES:
        raise ValueError(f"unknown policy type {type_name!r}; known: {', '.join(POLICY_TYPES)}")
    module, cls = POLICY_TYPES[type_name].split(":")
    try:
        return getattr(importlib.import_module(module), cls)
    except ImportError as err:  # an optional extra (e.g. LeRobot) is missing: say which, in one line
        raise PolicyUnavailable(f"policy type {type_name!r}: {str(err).splitlines()[0]}") from err


def policy_config_class(type_name: str) -> type[PolicyConfig]:
    """The config class of policy type ``type_name`` (``policy.type`` of a run): a ValueError
    with one line if the type is unknown, needs a missing extra, builds only from a saved folder
    (a LeRobot VLA: ``--init FOLDER``) or lacks a setting the run reads."""
    cls = policy_class(type_name).config_class
    if not (isinstance(cls, type) and issubclass(cls, PolicyConfig)):
        raise ValueError(f"policy type {type_name!r} is built from a saved policy folder, not from settings: "
                         f"start from one with --init FOLDER (docs/lerobot.md)")
    if cls.type != type_name:  # it would be saved, and read back, as another type
        raise ValueError(f"policy type {type_name!r}: its config {cls.__name__} says type {cls.type!r}: declare "
                         f"`type: ClassVar[str] = {type_name!r}` in it")
    missing = missing_run_fields(cls)
    if missing:
        raise ValueError(f"policy type {type_name!r}: its config {cls.__name__} lacks {', '.join(missing)}, which a "
                         "run reads (stepnft.policies.configuration.RUN_FIELDS)")
    return cls


class Policy(nn.Module, ABC):
    """What every policy offers the collector, the algorithms and evaluation."""

    type: ClassVar[str]
    config_class: ClassVar[type]
    shares_prefix_in_update: ClassVar[bool] = False
    """Whether the update encodes each policy call's observation once and shares that context
    among the call's recorded denoising steps (``forward(..., context_rows=...)``), with
    minibatches of whole calls. True for the LeRobot VLAs, whose prefix (vision encoder and VLM
    layers) costs far more than a denoising step. False keeps the per-step path, one encoding
    per recorded step in minibatches of steps: the MLP's published results depend on its random
    streams and float sums, which this keeps bit for bit."""
    checkpoints_layers: ClassVar[bool] = False
    """Whether :meth:`set_gradient_checkpointing` checkpoints inside the model (a VLA, per
    transformer layer) rather than the encoder and denoiser as two segments."""

    def __init__(self, config):
        super().__init__()
        self.config = config
        self.processor = self.make_processor(config)
        self.precision = "fp32"
        """``fp32`` or ``bf16`` (:meth:`set_precision`)."""
        self.gradient_checkpointing = False
        """Whether gradient passes recompute activations instead of keeping them (:meth:`set_gradient_checkpointing`)."""

    # --- what a policy implements -----------------------------------------------------------
    @staticmethod
    @abstractmethod
    def make_processor(config) -> Any:
        """The input processor of this policy (see ``stepnft.policies.processor``)."""

    @abstractmethod
    def encode(self, obs: dict[str, Tensor]) -> Any:
        """Observation context from processed ``obs`` (batch ``B``); computed once per call."""

    @abstractmethod
    def denoise(self, context: Any, x_t: Tensor, t: Tensor) -> Tensor:
        """Velocity ``[B, H, A]`` at ``x_t`` ``[B, H, A]``, ``t`` ``[B]`` given the context."""

    # --- what every policy gets -------------------------------------------------------------
    @property
    def chunk_shape(self) -> tuple[int, int]:
        return self.config.horizon, self.config.action_dim

    @property
    def device(self) -> torch.device:
        """Where the policy's weights live (``--device``; the processor stays on the CPU)."""
        return next(self.parameters()).device

    def prepare(self, raw: dict[str, Tensor]) -> dict[str, Tensor]:
        """Raw CPU observations -> model inputs on the policy's device: processed on the CPU
        (``self.processor``), then moved."""
        return to_device(self.processor(raw), self.device)

    # --- memory: precision and gradient checkpointing ---------------------------------------------
    def set_precision(self, precision: str) -> "Policy":
        """``bf16``: frozen floating-point parameters (a VLA's vision-language backbone with
        ``train: expert``) are stored in bfloat16, half their float32 memory, and every forward
        pass runs under ``torch.autocast(bfloat16)``; trained parameters stay float32 (the
        optimizer's master copy) and velocities and value features leave the model as float32, so
        the samplers' noise arithmetic and the losses (energies, their difference) are float32.
        ``fp32``: the frozen parameters back in float32, no autocast."""
        if precision not in PRECISIONS:
            raise ValueError(f"precision={precision!r} is invalid: use {' or '.join(PRECISIONS)}")
        dtype = torch.bfloat16 if precision == "bf16" else torch.float32
        note = bf16_capped_note() if precision == "bf16" and self.device.type == "cpu" else None
        if note is not None:
            warnings.warn(note, RuntimeWarning, stacklevel=2)
        for param in self.parameters():
            if not param.requires_grad and param.is_floating_point():
                param.data = param.data.to(dtype)
        self.precision = precision
        return self

    def autocast(self) -> contextlib.AbstractContextManager:
        """The context every forward pass of this policy runs in (see :meth:`set_precision`)."""
        if self.precision == "fp32":
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=torch.bfloat16)

    def set_gradient_checkpointing(self, enabled: bool) -> "Policy":
        """Recompute activations in the backward pass instead of keeping them from the forward
        pass: less memory, one more forward pass per update step, the same gradients. Here the
        encoder and the denoiser are each one checkpointed segment (peak memory: the larger of
        the two instead of both); a LeRobot VLA checkpoints every transformer layer."""
        self.gradient_checkpointing = bool(enabled)
        return self

    def _checkpointed(self, fn, *args):
        """``fn(*args)``, recomputed in backward when gradient checkpointing is on."""
        if self.gradient_checkpointing and not self.checkpoints_layers:
            return recompute(fn, *args)
        return fn(*args)

    def select_context(self, context: Any, rows: Tensor) -> Any:
        """The context of rows ``rows`` ``[R]`` (indices into its batch, repeats allowed) of an
        encoded ``context``: how one encoding per policy call serves each of its recorded steps.
        Here a tensor's rows; a policy whose context is another structure (a KV cache and its
        masks) overrides it. Gradients flow back to the shared encoding."""
        return context[rows]

    def velocity(self, obs: dict[str, Tensor], x_t: Tensor, t: Tensor) -> Tensor:
        """``v_θ(x_t, t | o)`` for processed ``obs``: the training forward pass (float32 out)."""
        return self.forward(obs, x_t, t)

    def forward(self, obs: dict[str, Tensor], x_t: Tensor, t: Tensor, context_rows: Tensor | None = None) -> Tensor:
        """:meth:`velocity`; with ``context_rows`` ``[R]``, ``obs`` holds one row per policy call
        and step ``i`` (``x_t[i]``, ``t[i]``) reads call ``context_rows[i]``, encoded once for all
        of its steps (the update of a policy that :attr:`shares_prefix_in_update`)."""
        with self.autocast():
            context = self._checkpointed(self.encode, obs)
            if context_rows is not None:
                context = self.select_context(context, context_rows)
            return self._checkpointed(self.denoise, context, x_t, t).float()

    def value_features(self, obs: dict[str, Tensor]) -> Tensor:
        """``[B, F]`` features of processed ``obs`` that a value head reads (PPO's critic), with
        gradients into the encoder where it trains (the caller detaches them, or not: PPO's
        ``critic_shares_encoder``). Default: the context of :meth:`encode` flattened, for a policy
        whose context is one tensor; a policy whose context is something else (a VLA's key/value
        cache) overrides this."""
        context = self.encode(obs)
        if not torch.is_tensor(context):
            raise NotImplementedError(f"{type(self).__name__}.encode gives a {type(context).__name__}, not a feature "
                                      "tensor: the policy needs its own value_features for a value head")
        return context.flatten(1)

    def env_actions(self, chunk: Tensor) -> Tensor:
        """Sampled chunk ``[..., H, A]`` -> the actions the env executes (a LeRobot policy
        un-pads and un-normalises them); the identity here."""
        return chunk

    def model_actions(self, actions: Tensor) -> Tensor:
        """Env actions -> the space the policy samples chunks in (the SFT target); the identity here."""
        return actions

    @torch.no_grad()
    def sample(self, obs: dict[str, Tensor], noise_level: float = 0.0, generator: torch.Generator | None = None,
               stochastic_steps: str = "all", keep_path: bool = False, mean_correction: bool = True) -> ChunkSample:
        """Sample chunks ``[B, H, A]`` for processed ``obs`` (on the policy's device): ODE when
        ``noise_level = 0`` (evaluation), else Flow-SDE; the context is encoded once. The noise
        is drawn from the CPU ``generator`` and moved, whatever the device."""
        with self.autocast():
            context = self.encode(obs)

        def velocity(x: Tensor, t: Tensor) -> Tensor:
            with self.autocast():
                return self.denoise(context, x, t).float()

        batch = next(iter(obs.values())).shape[0]
        return sample_chunk(velocity, (batch, *self.chunk_shape),
                            num_steps=self.config.num_inference_steps, noise_level=noise_level, generator=generator,
                            stochastic_steps=stochastic_steps, device=self.device,
                            keep_path=keep_path, mean_correction=mean_correction)

    # --- save / load ---------------------------------------------------------------------------
    def save_pretrained(self, directory: str | Path) -> Path:
        """Write ``config.json``, ``model.safetensors`` and ``processor.safetensors`` into ``directory``."""
        weights = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}
        processor = {k: v.contiguous() for k, v in self.processor.state_dict().items()}
        bad = non_finite(weights | processor)
        if bad:
            raise ValueError(f"refusing to save a policy with non-finite values in {', '.join(bad[:3])}")
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        write_atomic(directory / CONFIG_NAME, json.dumps({"type": self.type, **self.config.to_dict()}, indent=2))
        write_atomic(directory / WEIGHTS_NAME, save(weights))
        write_atomic(directory / PROCESSOR_NAME, save(processor))
        return directory

    @classmethod
    def from_pretrained(cls, directory: str | Path, map_location: str = "cpu") -> "Policy":
        """Load a saved policy of any registered type (or of ``cls``'s type when called on a
        subclass); a ValueError with one line if the folder is missing, corrupt or another type."""
        directory = Path(directory)
        if not (directory / CONFIG_NAME).is_file():
            raise FileNotFoundError(f"no policy checkpoint at {directory}: expected {CONFIG_NAME} and {WEIGHTS_NAME}")
        try:
            data = _config_data(directory)
            type_name = data.pop("type", "flow")
            target = policy_class(type_name)
            if cls is not Policy and not issubclass(target, cls):
                raise ValueError(f"it holds a {type_name!r} policy, not a {cls.type!r} one")
            return target.load_folder(directory, data, map_location)
        except (ValueError, TypeError, KeyError, RuntimeError, OSError, SafetensorError, json.JSONDecodeError) as err:
            if isinstance(err, (FileNotFoundError, PolicyUnavailable)):
                raise
            raise ValueError(f"corrupt policy checkpoint at {directory}: {str(err).splitlines()[0]}") from err

    @classmethod
    def load_folder(cls, directory: Path, data: dict, map_location: str = "cpu") -> "Policy":
        """This policy from its folder; ``data`` is its config.json without ``type``. A policy
        saved in another layout (e.g. LeRobot's) overrides this and :meth:`save_pretrained`."""
        weights_path = directory / WEIGHTS_NAME
        if not weights_path.is_file():
            raise FileNotFoundError(f"no policy checkpoint at {directory}: expected {CONFIG_NAME} and {WEIGHTS_NAME}")
        policy = cls(cls.config_class.from_dict(data))
        weights = load_file(str(weights_path), device=map_location)
        bad = non_finite(weights)
        if bad:
            raise ValueError(f"non-finite values in {', '.join(bad[:3])}")
        processor_path = directory / PROCESSOR_NAME
        if processor_path.is_file():
            policy.processor.load_state_dict(load_file(str(processor_path)))
        else:  # saved before processors existed: the statistics were model buffers
            policy.processor.load_state_dict({k: weights.pop(k) for k in ("state_mean", "state_std")})
        policy.load_state_dict(weights)
        return policy

    @classmethod
    def read_config(cls, directory: Path):
        """The config of the policy saved in ``directory``, without building the policy."""
        data = _config_data(directory)
        data.pop("type", None)
        return cls.config_class.from_dict(data)


def _config_data(directory: Path) -> dict:
    """The JSON object in ``directory/config.json``; ValueError if it holds anything else."""
    data = json.loads(read_settings_text(directory / CONFIG_NAME, "policy config"))
    if not isinstance(data, dict):
        raise ValueError(f"{CONFIG_NAME} must hold a JSON object, not a {type(data).__name__}")
    return data


def load_policy(directory: str | Path) -> Policy:
    """A saved policy of any registered type."""
    return Policy.from_pretrained(directory)


def load_policy_config(directory: str | Path):
    """The config of a saved policy of any registered type (its sizes, ``n_exec``), without
    building it; a ValueError with one line if the folder holds no policy."""
    directory = Path(directory)
    if not (directory / CONFIG_NAME).is_file():
        raise FileNotFoundError(f"no policy checkpoint at {directory}: expected {CONFIG_NAME}")
    try:
        return policy_class(_config_data(directory).get("type", "flow")).read_config(directory)
    except PolicyUnavailable:
        raise
    except (ValueError, OSError, AttributeError, TypeError, KeyError, json.JSONDecodeError) as err:
        raise ValueError(f"corrupt policy checkpoint at {directory}: {str(err).splitlines()[0]}") from err


def make_policy(config) -> Policy:
    """A new policy from its config (the config's ``type`` picks the class)."""
    return policy_class(config.type)(config)
