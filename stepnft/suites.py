"""Out-of-distribution evaluation suites: ``ind``, ``vision``, ``semantic``, ``execution``.

Each suite is :func:`stepnft.evaluate.evaluate_policy` (ODE sampling, episode ``e`` of a task
from initial-state seed ``seed + e``, Wilson 95 % CIs) on a vector env whose episodes carry the
suite's held-out perturbations (``stepnft.envs.perturbations``): one perturbation per episode,
cycling through the suite's list, so a suite of 100 episodes per task gives each of its four
or five perturbations 20-25 episodes. ``ind`` is the training distribution: the env as the
config describes it, with its training randomisation (``env.randomize``) if any. Results are
deterministic under the seed, and paired across policies: the same episode seed gives the same
initial state and the same perturbation.

``vision`` needs a camera policy and ``semantic`` a language-conditioned one
(:func:`suite_applies`); ``semantic`` and ``execution`` apply to state policies too.

For a comparison table (``stepnft compare``)::

    results = evaluate_suites(policy, env_cfg, ["ind", "vision", "semantic", "execution"], episodes, seed)
    row = summarize_suites(results)   # {"ind": .., "vision": .. or None, ..., "ood_average": ..}
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from stepnft.envs import env_options, make_vec_env, simulator_for
from stepnft.envs.perturbations import OOD_SUITES, SUITES, Perturbations
from stepnft.evaluate import evaluate_policy, format_ci, format_table, record_videos
from stepnft.names import split_names
from stepnft.policies.base import Policy

SUITE_NAMES = tuple(SUITES)
"""``ind`` and the out-of-distribution suites, in table order."""


def suite_applies(suite: str, policy_config) -> tuple[bool, str]:
    """Whether ``suite`` can shift what a policy with ``policy_config`` sees, and if not why."""
    check_suites([suite])
    if suite == "vision" and not policy_config.cameras:
        return False, "a state policy sees no image (vision needs policy.cameras)"
    if suite == "semantic" and policy_config.lang_dim == 0:
        return False, "the policy takes no instruction (semantic needs policy.lang_dim > 0)"
    return True, ""


def check_suites(suites: Sequence[str]) -> list[str]:
    """Suite names from a list or comma-separated strings; a ValueError names the valid ones."""
    names = split_names(suites)
    unknown = [n for n in names if n not in SUITES]
    if unknown or not names:
        raise ValueError(f"unknown suite {unknown[0] if unknown else ''!r}; choose among: {', '.join(SUITES)}")
    return names


def env_for_policy(env_cfg, policy_config):
    """``env_cfg`` with the observations a saved policy needs: its cameras (when the config
    names none) and the state observation of its size."""
    sim = simulator_for(env_cfg)
    if env_cfg.cameras and env_cfg.cameras != policy_config.cameras:
        raise ValueError(f"the policy sees cameras {policy_config.cameras}, env.cameras is {env_cfg.cameras}: "
                         "drop --env.cameras (the policy's are used) or give the same list")
    choices = [env_cfg.state_obs, "full", "proprio"]
    state_obs = next((s for s in choices if _state_dim(sim, s) == policy_config.state_dim), None)
    if state_obs is None:
        raise ValueError(f"no {sim.label} state observation has the policy's {policy_config.state_dim} dimensions")
    return dataclasses.replace(env_cfg, cameras=list(policy_config.cameras), state_obs=state_obs)


def _state_dim(sim, state_obs: str) -> int | None:
    try:
        return sim.state_dim_for(state_obs)
    except ValueError:
        return None


def suite_perturbations(suite: str) -> Perturbations | None:
    """The held-out perturbations of ``suite`` (None for ``ind``: the config's own)."""
    check_suites([suite])
    return Perturbations(SUITES[suite], heldout=True) if SUITES[suite] else None


def evaluate_suite(policy: Policy, env_cfg, suite: str, episodes: int, seed: int = 0, progress=None,
                   cache_dir: str | Path | None = None) -> dict:
    """Success per task of ``policy`` on ``suite`` (see the module doc): the result of
    :func:`~stepnft.evaluate.evaluate_policy` plus ``"suite"`` and, for a perturbation suite,
    ``"breakdown"`` (success per perturbation over all tasks). ``env_cfg`` is an
    ``EnvConfig`` (tasks, envs_per_task, num_workers, max_episode_steps, ...); its cameras and
    state observation follow the policy. The policy's instruction binding is restored after."""
    applies, reason = suite_applies(suite, policy.config)
    if not applies:
        raise ValueError(f"the {suite} suite does not apply to this policy: {reason}")
    env_cfg = env_for_policy(env_cfg, policy.config)
    perturbations = suite_perturbations(suite)
    venv = make_vec_env(env_cfg, policy.config.n_exec, seed, perturbations)
    try:
        with policy.processor.bound(venv.instruction_variants, cache_dir):
            result = evaluate_policy(policy, venv, episodes, seed, progress,
                                     label=perturbations.pick if perturbations else None)
    finally:
        venv.close()
    return {"suite": suite, **result}


def evaluate_suites(policy: Policy, env_cfg, suites: Sequence[str], episodes: int, seed: int = 0, progress=None,
                    cache_dir: str | Path | None = None) -> dict:
    """:func:`evaluate_suite` for each of ``suites``; those that do not apply to the policy are
    ``{"skipped": reason}``. Returns ``{"suites": {name: result}, "ood_average": mean success
    over the applicable vision / semantic / execution suites (None if none)}``."""
    results = {}
    for suite in check_suites(suites):
        applies, reason = suite_applies(suite, policy.config)
        results[suite] = (evaluate_suite(policy, env_cfg, suite, episodes, seed, progress, cache_dir) if applies
                          else {"suite": suite, "skipped": reason})
    return {"suites": results, "ood_average": summarize_suites(results)["ood_average"]}


def summarize_suites(results: dict) -> dict[str, float | None]:
    """Average success per suite (None where skipped or not run) and the OOD average (mean of
    the vision, semantic and execution figures present)."""
    row = {s: (results[s]["average"] if s in results and "average" in results[s] else None) for s in SUITE_NAMES}
    ood = [row[s] for s in OOD_SUITES if row[s] is not None]
    row["ood_average"] = float(np.mean(ood)) if ood else None
    return row


def format_suites(results: dict) -> str:
    """A plain-text table of :func:`evaluate_suites`'s results: success per task and suite."""
    suites = list(results["suites"])
    ran = [s for s in suites if "tasks" in results["suites"][s]]
    tasks = list(results["suites"][ran[0]]["tasks"]) if ran else []
    cell = lambda r: format_ci((r["success"], *r["ci95"]))  # noqa: E731
    lines = [f"{'task':<18}" + "".join(f"{s:>20}" for s in suites)]
    for task in tasks:
        lines.append(f"{task:<18}" + "".join(f"{cell(results['suites'][s]['tasks'][task]) if s in ran else '-':>20}"
                                             for s in suites))
    summary = summarize_suites(results["suites"])
    lines.append(f"{'average':<18}" + "".join(f"{'-' if summary[s] is None else f'{summary[s]:.3f}':>20}"
                                              for s in suites))
    ood = results["ood_average"]
    lines.append(f"OOD average: {'-' if ood is None else f'{ood:.3f}'}")
    for s in suites:
        if s not in ran:
            lines.append(f"{s} skipped: {results['suites'][s]['skipped']}")
    return "\n".join(lines)


def format_suite(result: dict) -> str:
    """One suite's table (task, success [95 % CI]) and its per-perturbation breakdown."""
    text = format_table(None, result)
    for name, r in result.get("breakdown", {}).items():
        text += f"\n  {name:<16} {format_ci((r['success'], *r['ci95']))} ({r['episodes']} episodes)"
    return text


def record_suite_videos(policy: Policy, env_cfg, suite: str, out_dir: str | Path, seed: int = 0, episodes: int = 1,
                        cache_dir: str | Path | None = None) -> list[Path]:
    """Film ``episodes`` ODE episodes per task under ``suite`` (the same episodes as
    :func:`evaluate_suite`'s first ones) into ``out_dir``."""
    env_cfg = env_for_policy(env_cfg, policy.config)
    sim = simulator_for(env_cfg)
    perturbations = suite_perturbations(suite)
    options = env_options(env_cfg, perturbations)
    variants = [sim.instruction_variants(t, options.get("perturbations")) for t in env_cfg.tasks]
    with policy.processor.bound(variants, cache_dir):
        return record_videos(policy, sim, env_cfg.tasks, out_dir, seed=seed, episodes=episodes,
                             max_episode_steps=env_cfg.max_episode_steps, env_options=options)
