"""Scripted-expert demonstrations for MetaWorld: generation, on-disk format, loading, SFT chunks.

On-disk format, version 1 (a public contract; bump "version" when it changes):

    out_dir/manifest.json
        {"format": "stepnft-demos", "version": 1,
         "tasks": [task, ...],                                  # in generation order
         "episodes": [{"file": "pick-place-v3/episode_0000.npz", # relative to out_dir
                       "task": str, "instruction": str,
                       "success": bool, "length": T, "seed": int}, ...],
         "generator": {...}}                                    # arguments, for provenance
    out_dir/<task>/episode_<k>.npz, one per episode, with
        observations  float32 [T+1, 39]  o_0 .. o_T (o_T is the state after the last action)
        actions       float32 [T, 4]     what was executed: expert action + noise, clipped
        rewards       float32 [T]
        successes     bool    [T]        success reached by step t (the episode stops at
                                         the first success, so only the last can be True)

Files are written to a temporary name and renamed, and the manifest last, so a crash never
leaves a half-written file behind a valid manifest.

Seeds. Episode k of a task starts from `MetaWorldChunkEnv.reset(seed=demo_seed(seed, k))`,
i.e. 2**32 + seed * 2**20 + k. Evaluation uses small seeds and the vector env's sub-env
streams are seeded below 2**32, so demo initial states never coincide with theirs.
"""

import dataclasses
import io
import json
import os
import tempfile
import warnings
from collections.abc import Sequence
from importlib.metadata import version
from pathlib import Path

import numpy as np
import torch
from metaworld.policies import ENV_POLICY_MAP
from tqdm import tqdm

from stepnft.envs.instructions import instruction_for
from stepnft.envs.metaworld import (
    ACTION_DIM,
    OBS_DIM,
    TASK_NAMES,
    MetaWorldChunkEnv,
    validate_tasks,
)

FORMAT = "stepnft-demos"
VERSION = 1
DEMO_SEED_OFFSET = 2**32
MAX_EPISODES_PER_TASK = 2**20


@dataclasses.dataclass
class DemoEpisode:
    """One demonstration; T is its number of actions."""

    task: str
    instruction: str
    observations: np.ndarray
    """float32 [T+1, 39]"""
    actions: np.ndarray
    """float32 [T, 4]"""
    rewards: np.ndarray
    """float32 [T]"""
    successes: np.ndarray
    """bool [T]"""
    success: bool
    seed: int


def demo_seed(seed: int, episode: int) -> int:
    """The reset seed of demo `episode` of every task in a run with `seed`."""
    return DEMO_SEED_OFFSET + seed * MAX_EPISODES_PER_TASK + episode


def generate_demos(
    tasks: str | Sequence[str],
    episodes: int,
    out_dir: str | Path,
    seed: int = 0,
    action_noise: float = 0.0,
    max_episode_steps: int = 200,
    progress: bool = True,
) -> Path:
    """Runs MetaWorld's scripted expert for `episodes` episodes per task; returns `out_dir`.

    Episodes end at the first success or after `max_episode_steps` steps. Gaussian noise of
    std `action_noise` is added to each expert action before clipping to [-1, 1].
    """
    tasks = validate_tasks(tasks)
    if not 1 <= episodes <= MAX_EPISODES_PER_TASK:
        raise ValueError(f"episodes must be in [1, {MAX_EPISODES_PER_TASK}], got {episodes}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    if action_noise < 0:
        raise ValueError(f"action_noise must be >= 0, got {action_noise}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    entries = []
    bar = tqdm(total=len(tasks) * episodes, desc="demos", unit="episode", disable=not progress)
    for task in tasks:
        env = MetaWorldChunkEnv(task, n_exec=1, max_episode_steps=max_episode_steps)
        expert = ENV_POLICY_MAP[task]()
        # A noise stream per (seed, task), unaffected by which other tasks are generated.
        noise_rng = np.random.default_rng([seed, TASK_NAMES.index(task)])
        (out_dir / task).mkdir(exist_ok=True)
        n_success = 0
        for k in range(episodes):
            episode = _run_expert(env, expert, noise_rng, action_noise, demo_seed(seed, k))
            file = f"{task}/episode_{k:04d}.npz"
            buffer = io.BytesIO()
            np.savez(
                buffer,
                observations=episode.observations,
                actions=episode.actions,
                rewards=episode.rewards,
                successes=episode.successes,
            )
            _write_atomic(out_dir / file, buffer.getvalue())
            entries.append(
                {
                    "file": file,
                    "task": task,
                    "instruction": episode.instruction,
                    "success": episode.success,
                    "length": len(episode.actions),
                    "seed": episode.seed,
                }
            )
            n_success += episode.success
            bar.update()
            bar.set_postfix(task=task, success_rate=f"{n_success / (k + 1):.2f}")
        env.close()
    bar.close()

    manifest = {
        "format": FORMAT,
        "version": VERSION,
        "tasks": tasks,
        "episodes": entries,
        "generator": {
            "episodes_per_task": episodes,
            "seed": seed,
            "action_noise": action_noise,
            "max_episode_steps": max_episode_steps,
            "expert": "metaworld.policies.ENV_POLICY_MAP",
            "metaworld_version": version("metaworld"),
        },
    }
    _write_atomic(out_dir / "manifest.json", json.dumps(manifest, indent=1).encode())
    return out_dir


def _run_expert(
    env: MetaWorldChunkEnv, expert, noise_rng: np.random.Generator, action_noise: float, seed: int
) -> DemoEpisode:
    obs, _ = env.reset(seed=seed)
    observations, actions, rewards, successes = [obs], [], [], []
    done = False
    while not done:
        with warnings.catch_warnings():
            # The experts warn when their gains saturate an action; we clip it anyway.
            warnings.filterwarnings("ignore", "Constant", UserWarning)
            action = expert.get_action(obs)
        if action_noise > 0:
            action = action + noise_rng.normal(0.0, action_noise, size=ACTION_DIM)
        action = np.clip(action, -1.0, 1.0).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(action[None])
        observations.append(obs)
        actions.append(action)
        rewards.append(reward)
        successes.append(info["success"])
        done = terminated or truncated
    return DemoEpisode(
        task=env.task,
        instruction=env.instruction,
        observations=np.stack(observations).astype(np.float32),
        actions=np.stack(actions),
        rewards=np.asarray(rewards, dtype=np.float32),
        successes=np.asarray(successes, dtype=bool),
        success=bool(successes[-1]),
        seed=seed,
    )


def _write_atomic(path: Path, data: bytes) -> None:
    """Writes `data` to a temporary file next to `path`, then renames it to `path`."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def load_demos(path: str | Path) -> list[DemoEpisode]:
    """Loads every episode listed in `path/manifest.json`, in manifest order."""
    path = Path(path)
    manifest_path = path / "manifest.json"
    if not manifest_path.is_file():
        raise FileNotFoundError(
            f"no demonstrations at {path}: run `stepnft demos --out {path}` first"
        )
    regenerate = f"run `stepnft demos --out {path}` to regenerate them"
    try:
        manifest = json.loads(manifest_path.read_text())
        if manifest.get("format") != FORMAT or manifest.get("version") != VERSION:
            raise ValueError(f"expected format {FORMAT!r} version {VERSION}")
        return [_load_episode(path, entry) for entry in manifest["episodes"]]
    except FileNotFoundError as e:
        raise FileNotFoundError(
            f"demonstrations at {path} are incomplete ({e}); {regenerate}"
        ) from None
    except (ValueError, KeyError, TypeError, AttributeError, OSError) as e:
        # Bad JSON is a ValueError; a damaged .npz raises ValueError, OSError or KeyError.
        raise ValueError(
            f"corrupt demonstrations at {path} ({type(e).__name__}: {e}); {regenerate}"
        ) from None


def _load_episode(root: Path, entry: dict) -> DemoEpisode:
    file = root / entry["file"]
    if not file.is_file():
        raise FileNotFoundError(f"missing {entry['file']}")
    with np.load(file) as data:
        arrays = {key: data[key] for key in ("observations", "actions", "rewards", "successes")}
    length = entry["length"]
    expected = {
        "observations": (length + 1, OBS_DIM),
        "actions": (length, ACTION_DIM),
        "rewards": (length,),
        "successes": (length,),
    }
    for key, shape in expected.items():
        if arrays[key].shape != shape:
            raise ValueError(
                f"{entry['file']}: {key} has shape {arrays[key].shape}, expected {shape}"
            )
    return DemoEpisode(
        task=entry["task"],
        instruction=entry["instruction"],
        observations=arrays["observations"].astype(np.float32),
        actions=arrays["actions"].astype(np.float32),
        rewards=arrays["rewards"].astype(np.float32),
        successes=arrays["successes"].astype(bool),
        success=bool(entry["success"]),
        seed=int(entry["seed"]),
    )


def demos_to_chunks(
    episodes: Sequence[DemoEpisode],
    tasks: Sequence[str],
    horizon: int,
    only_successful: bool = True,
) -> dict[str, torch.Tensor]:
    """The SFT dataset: one sample per time step t of every (successful) episode.

    Returns N samples:
        state    float32 [N, 39]    observations[t]
        task_id  int64   [N]        index of the episode's task in `tasks`
        actions  float32 [N, H, 4]  actions[t : t+H], past the episode's end repeating its
                                    last action
        mask     bool    [N, H]     False on those repeated (padded) positions
    """
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    task_index = {task: i for i, task in enumerate(tasks)}
    states, task_ids, chunks, masks = [], [], [], []
    for episode in episodes:
        if only_successful and not episode.success:
            continue
        if episode.task not in task_index:
            raise ValueError(f"demonstration task {episode.task!r} is not in tasks {list(tasks)}")
        length = len(episode.actions)
        # steps[t, h] = t + h: the action index each chunk position would take.
        steps = np.arange(length)[:, None] + np.arange(horizon)[None, :]
        states.append(episode.observations[:length])
        task_ids.append(np.full(length, task_index[episode.task], dtype=np.int64))
        chunks.append(episode.actions[np.minimum(steps, length - 1)])
        masks.append(steps < length)
    if not states:
        kind = "successful " if only_successful else ""
        raise ValueError(f"no {kind}demonstrations to build chunks from")
    return {
        "state": torch.from_numpy(np.concatenate(states).astype(np.float32)),
        "task_id": torch.from_numpy(np.concatenate(task_ids)),
        "actions": torch.from_numpy(np.concatenate(chunks).astype(np.float32)),
        "mask": torch.from_numpy(np.concatenate(masks)),
    }
