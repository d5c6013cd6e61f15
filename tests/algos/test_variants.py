"""Named variants: what each one builds on top of a base config."""

import dataclasses

import pytest
import yaml

from stepnft.algos.grpo import GRPOConfig
from stepnft.algos.ppo import PPOConfig
from stepnft.algos.stepnft import StepNFTConfig
from stepnft.algos.variants import PAPER_ALGO, SHARED_FIELDS, VARIANTS, describe_variants, reward_signal, variant_config
from stepnft.config import load_config

BASE = StepNFTConfig(noise_level=0.5, lr=2e-4, update_epochs=3, label_balance="global", record_steps="all")


def test_stepnft_variants_keep_the_base_and_change_only_their_switch():
    assert variant_config("stepnft", BASE) == BASE
    assert variant_config("wmse", BASE) == dataclasses.replace(BASE, form="wmse")
    assert variant_config("x0", BASE) == dataclasses.replace(BASE, target="x0")
    assert variant_config("ode", BASE) == dataclasses.replace(BASE, noise_level=0.0)
    assert variant_config("beta-2", BASE).beta == 2.0
    assert variant_config("ema-off", BASE).ema_target == 0.0
    assert variant_config("beta-5", BASE).beta == 5.0
    assert variant_config("pos-only", BASE) == dataclasses.replace(BASE, form="pos")
    assert variant_config("neg-only", BASE) == dataclasses.replace(BASE, form="neg")
    plain = variant_config("sde-plain", BASE)
    assert plain == dataclasses.replace(BASE, mean_correction=False)
    assert plain.rollout_spec().mean_correction is False and BASE.rollout_spec().mean_correction is True


def test_baselines_keep_the_shared_settings_only():
    ppo = variant_config("ppo", BASE)
    assert isinstance(ppo, PPOConfig) and ppo.name == "ppo"
    assert (ppo.lr, ppo.update_epochs, ppo.noise_level) == (2e-4, 3, 0.5)
    assert ppo.sde_steps == "all" and variant_config("ppo-one", BASE).sde_steps == "one"
    shared = variant_config("ppo-shared", BASE)  # the camera comparison's second critic
    assert ppo.critic_shares_encoder is False and shared == dataclasses.replace(ppo, critic_shares_encoder=True)
    grpo = variant_config("grpo-one", BASE)
    assert isinstance(grpo, GRPOConfig) and grpo.sde_steps == "one" and grpo.lr == 2e-4
    # Back from a PPO base, π-StepNFT gets the shared fields and its own defaults otherwise.
    back = variant_config("stepnft", ppo)
    assert isinstance(back, StepNFTConfig) and back.lr == 2e-4 and back.label_balance == StepNFTConfig().label_balance
    assert "noise_level" in SHARED_FIELDS and "label_balance" not in SHARED_FIELDS
    # What tells variants apart, or is valid per algorithm, keeps the variant's own defaults.
    assert not {"name", "sde_steps", "group_size"} & set(SHARED_FIELDS)
    grouped = dataclasses.replace(BASE, sde_steps="one", record_steps="one", group_size=2)
    assert (variant_config("ppo", grouped).sde_steps, variant_config("grpo", grouped).group_size) == ("all", 4)


def test_paper_variant_is_configs_paper_yaml():
    raw = yaml.safe_load(open("configs/paper.yaml"))["algo"]
    paper = load_config("configs/paper.yaml").algo
    for key, value in PAPER_ALGO.items():
        assert key in raw, key
        assert getattr(paper, key) == value, key
    assert variant_config("paper", BASE) == dataclasses.replace(paper, lr=BASE.lr, update_epochs=BASE.update_epochs,
                                                                minibatch_size=BASE.minibatch_size)


def test_every_variant_builds_and_is_described():
    base = load_config("configs/quickstart.yaml").algo
    for name in VARIANTS:
        variant_config(name, base)
        assert name in describe_variants()
    with pytest.raises(ValueError, match="unknown variant"):
        variant_config("sac", base)


@pytest.mark.parametrize("name", ["ppo", "grpo"])
def test_baseline_configs_are_the_compared_variants(name):
    """configs/ppo.yaml and configs/grpo.yaml are what `stepnft compare --algos ppo,grpo` runs on the
    quickstart: the variant's algo settings, and everything else the quickstart's."""
    quickstart = load_config("configs/quickstart.yaml")
    config = load_config(f"configs/{name}.yaml")
    assert config.algo == variant_config(name, quickstart.algo)
    assert dataclasses.replace(config, run_dir=quickstart.run_dir, algo=quickstart.algo) == quickstart


def test_shaped_baselines_read_the_signal_of_progress_labels():
    progress = dataclasses.replace(BASE, labels="progress")
    assert reward_signal(progress) == "success + shaped"
    for name, plain in (("ppo-shaped", "ppo"), ("ppo-shared-shaped", "ppo-shared"), ("grpo-shaped", "grpo")):
        shaped = variant_config(name, progress)
        assert reward_signal(variant_config(plain, progress)) == "success"  # the plain baselines stay sparse
        assert shaped == dataclasses.replace(variant_config(plain, progress), reward="shaped")
        assert reward_signal(shaped) == "success + shaped"
