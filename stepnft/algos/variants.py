"""Named variants: a name (``stepnft compare --algos NAME,...``) -> an algorithm and the config
overrides that make it, applied on top of a base run config's ``algo`` section. The ablations of
π-StepNFT run on its own code path, each one switch away (docs/algorithm.md §6); the baselines
are the other registered algorithms (§7). ``stepnft compare --help`` lists them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from stepnft.algos.base import ALGORITHMS, AlgoConfig, config_class
from stepnft.plugins import PluginRegistry


@dataclass(frozen=True)
class Variant:
    algo: str
    """The registered algorithm (``stepnft.algos.base.ALGORITHMS``)."""
    about: str
    """One line for ``--help`` and docs/baselines.md."""
    overrides: dict[str, Any] = field(default_factory=dict)
    """``algo.*`` fields set on top of the base config."""


PAPER_ALGO: dict[str, Any] = {
    "noise_level": 0.2, "beta": 1.0, "beta_dpo": 1.0, "max_drift": 0.5, "kl_beta": 1e-4, "target": "next",
    "form": "rank", "sde_steps": "all", "record_steps": "one", "labels": "episode", "label_balance": "none",
    "episode_weighting": False, "drift_limit": None, "ema_base": 0.1, "ema_target": 0.995, "eval_ema": True,
    "adam_betas": (0.9, 0.95), "adam_eps": 1e-5, "weight_decay": 0.01, "grad_clip": 1.0,
}
"""The paper's π-StepNFT settings (docs/algorithm.md §9), the ``algo`` section of
configs/paper.yaml; the learning rate, epochs and minibatch stay the base config's (the paper's
lr 1e-5 is for a 3B VLA and 64-128 envs)."""

def _check_variant(value) -> str | None:
    if not isinstance(value, Variant):
        what = f"the class {value.__name__}" if isinstance(value, type) else f"a {type(value).__name__}"
        return f"its entry point must name a stepnft.algos.variants.Variant, not {what}"
    return None


VARIANTS: dict[str, Variant] = PluginRegistry("stepnft.variants", {
    "stepnft": Variant("stepnft", "π-StepNFT with the base config's (tuned) settings"),
    "paper": Variant("stepnft", "π-StepNFT with the paper's settings (configs/paper.yaml)", PAPER_ALGO),
    "ode": Variant("stepnft", "ablation: ODE exploration (noise 0): no ranking signal", {"noise_level": 0.0}),
    "sde-plain": Variant("stepnft", "ablation: SDE exploration without the mean correction (noise on the Euler step)",
                         {"mean_correction": False}),
    "x0": Variant("stepnft", "ablation: final-action target x0 instead of the next step", {"target": "x0"}),
    "wmse": Variant("stepnft", "ablation: DiffusionNFT weighted MSE instead of the ranking", {"form": "wmse"}),
    "pos-only": Variant("stepnft", "ablation: the positive branch alone, r E_pos", {"form": "pos"}),
    "neg-only": Variant("stepnft", "ablation: the negative branch alone, (1 - r) E_neg", {"form": "neg"}),
    "beta-0.5": Variant("stepnft", "ablation: trust factor β = 0.5", {"beta": 0.5}),
    "beta-2": Variant("stepnft", "ablation: trust factor β = 2", {"beta": 2.0}),
    "beta-5": Variant("stepnft", "ablation: trust factor β = 5", {"beta": 5.0}),
    "noise-0.2": Variant("stepnft", "ablation: noise level a = 0.2 (the paper's)", {"noise_level": 0.2}),
    "noise-1": Variant("stepnft", "ablation: noise level a = 1.0", {"noise_level": 1.0}),
    "ema-off": Variant("stepnft", "ablation: no EMA, the trained policy acts (decay 0)",
                       {"ema_base": 0.0, "ema_target": 0.0}),
    "ema-slow": Variant("stepnft", "ablation: slower EMA, decay 0.5 -> 0.999", {"ema_base": 0.5, "ema_target": 0.999}),
    "progress": Variant("stepnft", "per-call labels: outcome mixed with the call's shaped-reward progress",
                        {"labels": "progress"}),
    "episode-labels": Variant("stepnft", "ablation: one ±1 outcome label per episode (the paper's labels)",
                              {"labels": "episode"}),
    "ppo": Variant("ppo", "PPO with Flow-SDE and a critic, every denoising step stochastic"),
    "ppo-one": Variant("ppo", "PPO with Flow-SDE, one stochastic step per call (πRL)", {"sde_steps": "one"}),
    "ppo-shared": Variant("ppo", "PPO whose value head shares the policy's encoder and trains it (a value head on a VLA)",
                          {"critic_shares_encoder": True}),
    "grpo": Variant("grpo", "GRPO with Flow-SDE, group-normalised success, every step stochastic (lr 3e-5)",
                    {"lr": 3e-5}),  # tuned: at 1e-4 its ~24 steps per iteration move too far (experiments §12)
    "grpo-one": Variant("grpo", "GRPO with Flow-SDE, one stochastic step per call", {"sde_steps": "one"}),
    # The baselines on the signal π-StepNFT's progress labels read (the simulator's shaped reward
    # too), so a comparison's pairs learn from the same information (suites.md's reward column).
    "ppo-shaped": Variant("ppo", "ppo on the shaped reward too (the signal of π-StepNFT's progress labels)",
                          {"reward": "shaped"}),
    "ppo-shared-shaped": Variant("ppo", "ppo-shared on the shaped reward too",
                                 {"critic_shares_encoder": True, "reward": "shaped"}),
    "grpo-shaped": Variant("grpo", "grpo on the shaped reward too (lr 3e-5)", {"lr": 3e-5, "reward": "shaped"}),
}, load=True, check=_check_variant)
"""Every variant ``stepnft compare`` knows: stepnft's own and those of installed packages
(entry-point group ``stepnft.variants`` naming a :class:`Variant`, ``stepnft.plugins``). A new
one here adds a line. Any registered algorithm's name is a variant too (:func:`get_variant`)."""


def variant_names() -> list[str]:
    """Every name :func:`get_variant` takes: the variants, then the algorithms that are none."""
    return [*VARIANTS, *(a for a in ALGORITHMS if a not in VARIANTS)]


def get_variant(name: str) -> Variant:
    """Variant ``name``: a registered one, or a registered algorithm with the base config's
    settings (a plugin algorithm: ``--algos myalgo``); a ValueError listing both otherwise."""
    if name in VARIANTS:
        return VARIANTS[name]
    if name in ALGORITHMS:
        return Variant(name, f"the registered algorithm {name!r} ({ALGORITHMS.sources.get(name, 'stepnft')})")
    raise ValueError(f"unknown variant {name!r}; choose from: {', '.join(variant_names())}")

SHARED_FIELDS = tuple(f.name for f in dataclasses.fields(AlgoConfig) if not f.metadata.get("per_variant"))
"""What a variant of another algorithm keeps from the base config: the settings every algorithm
has (``AlgoConfig``: the optimizer, the exploration noise), so every method starts from the same
choices; those marked ``PER_VARIANT`` (the name, ``sde_steps``, ``group_size``) keep the variant's."""


def variant_config(name: str, base: AlgoConfig) -> AlgoConfig:
    """The algo config of variant ``name`` on top of ``base``: all of ``base`` when it is the
    same algorithm, else its :data:`SHARED_FIELDS`; then the variant's overrides."""
    variant = get_variant(name)
    values = {f.name: getattr(base, f.name) for f in dataclasses.fields(base)}
    if base.name != variant.algo:
        values = {k: v for k, v in values.items() if k in SHARED_FIELDS}
    cls = config_class(variant.algo)
    known = {f.name for f in dataclasses.fields(cls)}
    values = {k: v for k, v in values.items() if k in known}
    return cls(**{**values, **variant.overrides, "name": variant.algo})


def reward_signal(cfg: AlgoConfig) -> str:
    """What ``cfg`` learns from, for the comparison table: ``success`` (the sparse outcome) or
    ``success + shaped`` (the simulator's shaped reward too: π-StepNFT's ``labels: progress``,
    PPO's and GRPO's ``reward: shaped``)."""
    shaped = getattr(cfg, "labels", None) == "progress" or getattr(cfg, "reward", None) == "shaped"
    return "success + shaped" if shaped else "success"


def describe_variants(indent: str = "  ") -> str:
    """One line per variant: its name, algorithm and what it is."""
    width = max(map(len, VARIANTS))
    return "\n".join(f"{indent}{name:<{width}}  [{v.algo}] {v.about}" for name, v in VARIANTS.items())
