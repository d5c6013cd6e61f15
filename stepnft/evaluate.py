"""Deterministic evaluation: ODE sampling on a fixed, seeded set of initial states.

Episode ``e`` of every task starts from initial state ``seed + e``, whatever the checkpoint or
algorithm, so figures from different runs are paired. Success rates come with a Wilson 95 %
confidence interval. :func:`record_videos` films ODE episodes from the same initial states
(for camera policies, what the policy saw beside the scene). Out-of-distribution suites are
``stepnft.suites``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from stepnft.devices import to_device
from stepnft.policies.base import Policy
from stepnft.rollout.collector import Collector
from stepnft.rollout.plan import EpisodePlan


def wilson_interval(successes: int, episodes: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (95 % for ``z = 1.96``)."""
    if episodes == 0:
        return 0.0, 1.0
    p = successes / episodes
    denom = 1 + z**2 / episodes
    centre = (p + z**2 / (2 * episodes)) / denom
    half = z * math.sqrt(p * (1 - p) / episodes + z**2 / (4 * episodes**2)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def evaluate_policy(policy: Policy, venv, episodes: int, seed: int = 0, progress=None,
                    label: Callable[[int], str] | None = None) -> dict:
    """Success per task over ``episodes`` episodes each, ODE sampling.

    ``venv`` is a chunk vector env, or a collector that plays on one (e.g. ``RayCollector``:
    the same episodes, on its workers). Episode ``e`` of every task starts from initial state
    ``seed + e`` (``EpisodePlan.fixed``). ``policy.processor`` must be bound to
    ``venv.instruction_variants`` (or ``venv.instructions``). ``progress(done, total)`` is
    called as episodes end. Returns ``{"tasks": {task: {...}}, "average": rate, "episodes": per
    task, "env_steps": total}``; with ``label`` (the initial state seed -> a group name, e.g. a
    suite's perturbation) also ``"breakdown": {group: {...}}`` over every task's episodes.
    """
    collector = venv if isinstance(venv, Collector) else Collector(venv)
    tasks = list(collector.venv.tasks)
    plan = EpisodePlan.fixed(len(tasks), episodes, seed)
    batch = collector.play(policy, plan, 0.0, progress=progress)
    success = batch.episode_success.numpy()
    rates = {name: _rate(success[plan.task == k].sum(), episodes) for k, name in enumerate(tasks)}
    result = {"tasks": rates, "average": float(np.mean([r["success"] for r in rates.values()])),
              "episodes": episodes, "env_steps": batch.env_steps}
    if label is not None:
        groups: dict[str, list[int]] = {}
        for s, ok in zip(plan.seed, success):
            tally = groups.setdefault(label(int(s)), [0, 0])
            tally[0], tally[1] = tally[0] + int(ok), tally[1] + 1
        result["breakdown"] = {g: _rate(k, n) for g, (k, n) in sorted(groups.items())}
    return result


def _rate(successes: int, episodes: int) -> dict:
    lo, hi = wilson_interval(int(successes), int(episodes))
    return {"success": float(successes / episodes), "successes": int(successes), "episodes": int(episodes),
            "ci95": [lo, hi]}


def difference_interval(before: dict, after: dict) -> tuple[float, float]:
    """95 % interval of ``after - before`` success rates (Newcombe's method from the two Wilson
    intervals; each argument a task's result: ``success`` and ``ci95``)."""
    p1, (l1, u1) = after["success"], after["ci95"]
    p2, (l2, u2) = before["success"], before["ci95"]
    d = p1 - p2
    return d - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2), d + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2)


def tasks_below(before: dict, after: dict) -> list[str]:
    """Tasks that ended below their start by more than the uncertainty: the 95 % interval of
    the difference (:func:`difference_interval`) lies wholly below zero."""
    return [t for t, r in after["tasks"].items() if difference_interval(before["tasks"][t], r)[1] < 0]


def episode_generators(seeds: list[int]) -> list[torch.Generator]:
    """The sampler generator of each evaluation episode, seeded by its initial-state seed: an
    episode's outcome depends only on the policy and that seed, not on the env layout."""
    return [torch.Generator().manual_seed(s) for s in seeds]


def format_ci(stats: tuple[float, float, float], signed: bool = False) -> str:
    """``mean [lo, hi]`` of a ``(mean, lo, hi)`` triple, two decimals (``–`` without a mean, no
    interval without bounds): the one way stepnft writes a figure with its 95 % interval.
    An evaluation result ``r`` gives ``format_ci((r["success"], *r["ci95"]))``."""
    mean, lo, hi = stats
    if math.isnan(mean):
        return "–"
    fmt = "{:+.2f}" if signed else "{:.2f}"
    return fmt.format(mean) + ("" if math.isnan(lo) else f" [{fmt.format(lo)}, {fmt.format(hi)}]")


def format_table(before: dict | None, after: dict) -> str:
    """A plain-text table: task, success before -> after with 95 % CIs (the task column as wide
    as the longest name, at least 18)."""
    cell = lambda r: format_ci((r["success"], *r["ci95"]))  # noqa: E731
    w = max([18, *map(len, after["tasks"])])
    if before is None:
        lines = [f"{'task':<{w}} {'success [95% CI]':>22}"]
        lines += [f"{task:<{w}} {cell(res):>22}" for task, res in after["tasks"].items()]
        lines.append(f"{'average':<{w}} {after['average']:>22.3f}")
        return "\n".join(lines)
    lines = [f"{'task':<{w}} {'before':>22} {'after':>22}"]
    for task, res in after["tasks"].items():
        lines.append(f"{task:<{w}} {cell(before['tasks'][task]):>22} {cell(res):>22}")
    lines.append(f"{'average':<{w}} {before['average']:>22.3f} {after['average']:>22.3f}")
    return "\n".join(lines)


def record_videos(
    policy: Policy,
    simulator,
    tasks: list[str],
    out_dir: str | Path,
    seed: int = 0,
    episodes: int = 1,
    max_episode_steps: int = 200,
    size: tuple[int, int] = (224, 224),
    env_options: dict | None = None,
    on_video: Callable[[str, list[np.ndarray]], None] | None = None,
) -> list[Path]:
    """Film ODE episodes as ``out_dir/<task>_ep<e>_<success|fail>.mp4``; returns the paths.

    Episode ``e`` of a task starts from evaluation initial state ``seed + e`` with the sampler
    noise of that episode in :func:`evaluate_policy`. A
    frame at reset and one after every env step (the chunk's actions are played one at a
    time), at the simulator's real-time rate. ``env_options`` (``stepnft.envs.env_options``:
    cameras, state, perturbations) build the filmed env like the evaluated one; for a camera
    policy each frame shows, right of the scene, the views the policy was last called with.
    ``policy.processor`` must be bound to ``tasks``' instructions (or instruction variants), in
    order. ``on_video(name, frames)`` receives each episode's frames (e.g. for TensorBoard).
    Raises :class:`~stepnft.envs.base.RenderingError` without offscreen rendering.
    """
    import imageio.v2 as imageio

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    policy.eval()
    paths = []
    for k, task in enumerate(tasks):
        env = simulator.make_env(task, n_exec=1, max_episode_steps=max_episode_steps, render_size=size,
                                 **(env_options or {}))
        try:
            for e in range(episodes):
                frames, success = _play_filmed(policy, env, k, seed + e, episode_generators([seed + e])[0])
                outcome = "success" if success else "fail"
                path = out_dir / f"{task}_ep{e}_{outcome}.mp4"
                tmp = out_dir / f".{path.stem}.tmp.mp4"
                with imageio.get_writer(tmp, fps=simulator.control_hz, codec="libx264") as writer:
                    for frame in frames:
                        writer.append_data(frame)
                os.replace(tmp, path)
                (out_dir / f"{task}_ep{e}_{'fail' if success else 'success'}.mp4").unlink(missing_ok=True)
                paths.append(path)
                if on_video is not None:
                    on_video(path.stem, frames)
        finally:
            env.close()  # frees the GL context now; MuJoCo's EGL complains if left to __del__
    return paths


def _play_filmed(policy: Policy, env, task_index: int, seed: int,
                 generator: torch.Generator) -> tuple[list[np.ndarray], bool]:
    """One ODE episode on a one-action chunk env; frames ``[H, W, 3]`` uint8 (the scene, and
    right of it the camera views of the last policy call, if any) and its success."""
    obs, info = env.reset(seed=seed)
    seen = obs.get("image")
    frames = [_beside(env.render(), seen)]
    done = False
    while not done:
        raw = {k: torch.as_tensor(np.asarray(v)[None]) for k, v in obs.items()} | {"task": torch.tensor([task_index])}
        seen = obs.get("image")
        sample = to_device(policy.sample(policy.prepare(raw), noise_level=0.0, generator=generator), "cpu")
        for action in policy.env_actions(sample.actions[0, : policy.config.n_exec]).clamp(-1.0, 1.0).numpy():
            obs, _, terminated, truncated, info = env.step(action[None])
            frames.append(_beside(env.render(), seen))
            done = terminated or truncated
            if done:
                break
    return frames, bool(info["success"])


def _beside(scene: np.ndarray, views: np.ndarray | None) -> np.ndarray:
    """The scene ``[H, W, 3]`` with camera views ``[V, 3, h, w]`` stacked right of it, each
    enlarged by a whole factor (nearest pixel) to fill the height."""
    if views is None:
        return scene
    height = scene.shape[0]
    v, _, h, w = views.shape
    k = max(1, height // (v * h))
    panel = views.transpose(0, 2, 3, 1).repeat(k, axis=1).repeat(k, axis=2).reshape(v * h * k, w * k, 3)[:height]
    panel = np.pad(panel, ((0, height - panel.shape[0]), (0, 0), (0, 0)))
    return np.concatenate([scene, panel], axis=1)
