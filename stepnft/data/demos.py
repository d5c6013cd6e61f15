"""Scripted-expert demonstrations: generation, on-disk format, loading, SFT chunks.

On-disk format, version 1 (a public contract; bump "version" when it changes):

    out_dir/manifest.json
        {"format": "stepnft-demos", "version": 1,
         "tasks": [task, ...],                                  # in generation order
         "episodes": [{"file": "pick-place-v3/episode_0000.npz", # relative to out_dir
                       "task": str, "instruction": str,
                       "success": bool, "length": T, "seed": int}, ...],
         "generator": {...}}                                    # arguments, for provenance
    out_dir/<task>/episode_<k>.npz, one per episode, with
        observations  float32 [T+1, S]   states o_0 .. o_T (o_T is the state after the last action)
        actions       float32 [T, A]     what was executed: expert action + noise, clipped
        rewards       float32 [T]
        successes     bool    [T]        success reached by step t (the episode stops at
                                         the first success, so only the last can be True)
        images        uint8   [T+1, V, 3, H, W]   only when generated with cameras: the camera
                                         views of o_0 .. o_T (upright, H = W = image_size)

``generator`` also names the ``simulator`` and its ``state_dim`` and ``action_dim``, and with
cameras ``cameras`` (names, in view order) and ``image_size``. Manifests written before a
second simulator existed name none of the three: their widths are checked against the
simulator :func:`load_demos` is given, if any. Files without images (and manifests without
``cameras``) are the same version-1 files as before images existed: they still load. Observations are always the
simulator's full state: a policy that sees less (``env.state_obs proprio``) is given its part
when SFT builds its chunks. Files are written to a temporary name and
renamed, and the manifest last, so a crash never leaves a half-written file behind a valid
manifest.

Generation keeps drawing initial states until it has ``episodes`` successful demonstrations per
task (scripted experts miss some episodes on harder tasks), at most ``max_attempts`` per task;
failed attempts are discarded and counted in the manifest (``generator.discarded``).

Seeds. Attempt k of a task starts from `reset(seed=demo_seed(seed, k))`, i.e.
2**32 + seed * 2**20 + k. Evaluation uses small seeds and the vector env's sub-env streams are
seeded below 2**32, so demo initial states never coincide with theirs.
"""

import json
import shutil
import sys
import zipfile
from collections.abc import Callable, Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from stepnft.envs import get_simulator
from stepnft.envs.episodes import DemoEpisode
from stepnft.provenance import changed_since, code_commit, code_version
from stepnft.runs import LOCK_NAME, check_folder, write_atomic, writer_lock
from stepnft.settings import DEMO_EPISODES_MAX

__all__ = ["DemoEpisode", "check_task_episodes", "demo_cameras", "demo_seed", "demos_to_chunks", "generate_demos",
           "load_demos", "load_or_generate_demos"]

FORMAT = "stepnft-demos"
VERSION = 1
DEMO_SEED_OFFSET = 2**32
MAX_EPISODES_PER_TASK = DEMO_EPISODES_MAX


def demo_seed(seed: int, episode: int) -> int:
    """The reset seed of demo attempt `episode` of every task in a run with `seed`."""
    return DEMO_SEED_OFFSET + seed * MAX_EPISODES_PER_TASK + episode


def generate_demos(
    tasks: str | Sequence[str],
    episodes: int,
    out_dir: str | Path,
    seed: int = 0,
    action_noise: float = 0.0,
    max_episode_steps: int = 200,
    progress: bool = True,
    *,
    simulator,
    dart: bool = False,
    max_attempts: int | None = None,
    successful_only: bool = True,
    cameras: Sequence[str] = (),
    image_size: int = 64,
) -> Path:
    """Runs the simulator's scripted expert until it has `episodes` successful episodes per
    task (at most `max_attempts` attempts per task, default 5 x `episodes`); returns `out_dir`.
    With `successful_only=False` it keeps the first `episodes` attempts, failed or not.

    Episodes end at the first success or after `max_episode_steps` steps. Gaussian noise of
    std `action_noise` is added to each expert action before clipping to [-1, 1]; the noisy
    action is recorded, or with `dart` the expert's clean one (DART: noise moves the states
    visited, the labels stay the expert's).
    `simulator` is a registered name or a :class:`~stepnft.envs.base.Simulator`. With
    `cameras`, every step's camera views are recorded too (``images``). `out_dir` must be new
    or empty, or hold a recording of the same settings that was interrupted: Ctrl-C or SIGTERM
    keep the tasks recorded whole (:class:`DemosInterrupted`), kill -9 leaves them too, and the
    same call continues with the next task, each task's episodes being the same as without the
    interruption (a task's seeds and noise depend on the seed and the task alone). If generation
    fails (a failing expert, bad input), the files it wrote are removed again.
    """
    sim = get_simulator(simulator) if isinstance(simulator, str) else simulator
    tasks = sim.validate_tasks(tasks)
    max_attempts = 5 * episodes if max_attempts is None else max_attempts
    _check_generation(episodes, max_attempts, seed, action_noise, dart)
    out_dir = Path(out_dir)
    if (out_dir / "manifest.json").is_file():
        raise ValueError(f"{out_dir} already holds demonstrations: choose another demonstrations folder "
                         "(--demos.path), or delete that one to regenerate it")
    settings = {"episodes_per_task": episodes, "max_attempts": max_attempts, "seed": seed, "action_noise": action_noise,
                **({"dart": True} if dart else {}), "max_episode_steps": max_episode_steps,
                **({"cameras": list(cameras), "image_size": image_size} if cameras else {})}
    recording = {"simulator": sim.name, "tasks": tasks, "successful_only": successful_only, **settings}
    finished = _interrupted_recording(out_dir, recording)  # None unless it continues one
    created = [d for d in (out_dir, *out_dir.parents) if not d.exists()]  # removed again if generation fails
    if finished is None:
        check_folder(out_dir, "demos", "--demos.path")
        finished = {}
    else:
        _remove_unfinished_tasks(out_dir, tasks)  # e.g. killed mid-task: that task is recorded again whole
        if progress:
            print(f"{out_dir}: continuing an interrupted recording ({len(finished)} of {len(tasks)} tasks recorded)",
                  file=sys.stderr)
    entries, discarded = [], {}
    with writer_lock(out_dir):
        write_atomic(out_dir / RECORDING, json.dumps(recording))
        try:
            with tqdm(total=len(tasks) * episodes, desc="demos", unit="episode", disable=not progress,
                      mininterval=1.0) as bar:
                for task in tasks:
                    if task in finished:  # recorded whole before an interruption: the same files
                        entries += finished[task]["entries"]
                        discarded[task] = finished[task]["discarded"]
                        bar.update(len(finished[task]["entries"]))
                        continue
                    mine: list[dict] = []
                    discarded[task] = _record_task(sim, task, out_dir, bar, successful_only=successful_only,
                                                   written=mine, **settings)
                    entries += mine
                    write_atomic(out_dir / task / TASK_DONE, json.dumps({"entries": mine, "discarded": discarded[task]}))
            write_atomic(out_dir / "manifest.json", json.dumps(_manifest(sim, tasks, entries, discarded, settings), indent=1))
            for task in tasks:
                (out_dir / task / TASK_DONE).unlink(missing_ok=True)
            (out_dir / RECORDING).unlink()
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the finished tasks stay, the same command continues
            _remove_unfinished_tasks(out_dir, tasks)
            raise DemosInterrupted(f"interrupted: {sum((out_dir / t / TASK_DONE).is_file() for t in tasks)} of "
                                   f"{len(tasks)} tasks recorded in {out_dir}; rerun the same command to continue "
                                   "the recording") from None
        except BaseException:  # bad input or a failing expert: nothing of this recording is left
            for task in tasks:
                if (out_dir / task).is_dir():
                    shutil.rmtree(out_dir / task)
            (out_dir / RECORDING).unlink(missing_ok=True)
            for folder in created:
                if folder.is_dir() and [p.name for p in folder.iterdir()] in ([], [LOCK_NAME]):
                    (folder / LOCK_NAME).unlink(missing_ok=True)
                    folder.rmdir()
            raise
    return out_dir


RECORDING = ".recording.json"
"""Hidden, while a recording runs or after it was interrupted: what it records (a rerun that asks for
the same continues it; :func:`_interrupted_recording`)."""
TASK_DONE = ".done.json"
"""Hidden, in ``out_dir/<task>/`` of an unfinished recording: the task's episodes are all on disk."""


class DemosInterrupted(KeyboardInterrupt):
    """A recording stopped by Ctrl-C or SIGTERM; its message says how to continue it."""


def _interrupted_recording(out_dir: Path, recording: dict) -> dict[str, dict] | None:
    """The finished tasks (their manifest entries and discarded attempts) of an interrupted
    recording in ``out_dir`` that asked for ``recording``; None when there is none. One that asked
    for something else is refused in one line (it is the user's to finish or delete) unless it
    finished no task yet: then it is cleared."""
    path = out_dir / RECORDING
    if not path.is_file():
        return None
    try:
        recorded = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        recorded = None
    if not isinstance(recorded, dict):
        raise ValueError(f"{out_dir} holds an interrupted recording whose {RECORDING} is unreadable: delete the "
                         f"folder (`rm -r {out_dir}`) to record again")
    if recorded != recording and not list(out_dir.glob(f"*/{TASK_DONE}")):
        for task in recorded.get("tasks", []) if isinstance(recorded.get("tasks"), list) else []:
            if isinstance(task, str) and task and "/" not in task and (out_dir / task).is_dir():
                shutil.rmtree(out_dir / task)
        path.unlink()
        return None
    if recorded != recording:
        changed = sorted(k for k in recording.keys() | recorded.keys() if recording.get(k) != recorded.get(k))
        raise ValueError(f"{out_dir} holds an interrupted recording with other settings ({', '.join(changed)}): "
                         "rerun the command that started it to finish it, or choose another --demos.path")
    finished = {}
    for task in recording["tasks"]:
        try:
            done = json.loads((out_dir / task / TASK_DONE).read_text())
        except (OSError, UnicodeDecodeError, ValueError):
            continue  # not finished (or torn): recorded again from its first attempt
        if isinstance(done, dict) and all((out_dir / e["file"]).is_file() for e in done.get("entries", [])):
            finished[task] = done
    return finished


def _remove_unfinished_tasks(out_dir: Path, tasks: list[str]) -> None:
    for task in tasks:
        if (out_dir / task).is_dir() and not (out_dir / task / TASK_DONE).is_file():
            shutil.rmtree(out_dir / task)


def _check_generation(episodes: int, max_attempts: int, seed: int, action_noise: float, dart: bool = False) -> None:
    if not 1 <= episodes <= MAX_EPISODES_PER_TASK:
        raise ValueError(f"episodes must be in [1, {MAX_EPISODES_PER_TASK}], got {episodes}")
    if not episodes <= max_attempts <= MAX_EPISODES_PER_TASK:
        raise ValueError(f"max_attempts must be in [episodes, {MAX_EPISODES_PER_TASK}], got {max_attempts}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    if not action_noise >= 0 or not np.isfinite(action_noise):
        raise ValueError(f"action_noise must be a finite number >= 0, got {action_noise}")
    if dart and not action_noise > 0:
        raise ValueError("dart records the expert's clean actions on states its noisy actions reach: give it an action "
                         "noise (--demos.action-noise 0.3 --demos.dart)")


def _record_task(sim, task: str, out_dir: Path, bar, *, episodes_per_task: int, max_attempts: int, seed: int,
                 action_noise: float, max_episode_steps: int, successful_only: bool, written: list[dict],
                 cameras: Sequence[str] = (), image_size: int = 64, dart: bool = False) -> int:
    """Expert attempts at ``task`` until ``episodes_per_task`` are kept, each written to
    ``out_dir/task/`` and its manifest entry appended to ``written`` as soon as it is on disk;
    returns the number of attempts discarded."""
    camera_options = {"cameras": list(cameras), "image_size": image_size} if cameras else {}
    expert = sim.expert(task, seed)  # first: a simulator without experts says so before building an env
    env = sim.make_env(task, n_exec=1, max_episode_steps=max_episode_steps, **camera_options)
    if hasattr(expert, "attach"):  # an Expert; a duck-typed one with act() alone reads only the observation
        expert.attach(env)
    # A noise stream per (seed, task), unaffected by which other tasks are generated.
    noise_rng = np.random.default_rng([seed, sim.task_names().index(task)])
    (out_dir / task).mkdir(exist_ok=True)
    entries, attempts = [], 0
    try:
        while len(entries) < episodes_per_task:
            if attempts == max_attempts:
                raise ValueError(f"the {sim.label} expert succeeded on only {len(entries)} of {attempts} attempts at "
                                 f"{task}: raise --demos.max-attempts above {max_attempts}, or ask for fewer than "
                                 f"{episodes_per_task} episodes (--demos.episodes); nothing was written")
            episode = _run_expert(env, sim.instruction(task), expert, noise_rng, action_noise,
                                  demo_seed(seed, attempts), task, dart)
            attempts += 1
            if successful_only and not episode.success:
                continue
            file = f"{task}/episode_{len(entries):04d}.npz"
            write_atomic(out_dir / file, _npz_bytes(episode))
            entries.append({"file": file, "task": task, "instruction": episode.instruction, "success": episode.success,
                            "length": len(episode.actions), "seed": episode.seed})
            written.append(entries[-1])
            bar.update()
            bar.set_postfix(task=task, discarded=attempts - len(entries), refresh=False)
    finally:
        env.close()
    return attempts - len(entries)


def _manifest(sim, tasks: list[str], entries: list[dict], discarded: dict[str, int], settings: dict) -> dict:
    try:
        package_version = version(sim.distribution or sim.name)
    except PackageNotFoundError:
        package_version = None
    generator = {"simulator": sim.name, "state_dim": sim.state_dim, "action_dim": sim.action_dim,
                 "episodes_per_task": settings["episodes_per_task"], "max_attempts": settings["max_attempts"],
                 "discarded": discarded, "seed": settings["seed"], "action_noise": settings["action_noise"],
                 "max_episode_steps": settings["max_episode_steps"], "expert": f"{sim.name} scripted expert",
                 "simulator_version": package_version, "code": code_version(),
                 **{k: settings[k] for k in ("dart", "cameras", "image_size") if k in settings}}
    return {"format": FORMAT, "version": VERSION, "tasks": tasks, "episodes": entries, "generator": generator}


def _npz_bytes(episode: DemoEpisode) -> bytes:
    import io

    buffer = io.BytesIO()
    images = {} if episode.images is None else {"images": episode.images}
    np.savez(buffer, observations=episode.observations, actions=episode.actions, rewards=episode.rewards,
             successes=episode.successes, **images)
    return buffer.getvalue()


def _run_expert(env, instruction: str, expert, noise_rng: np.random.Generator, action_noise: float, seed: int,
                task: str, dart: bool = False) -> DemoEpisode:
    obs, _ = env.reset(seed=seed)
    observations, actions, rewards, successes = [obs["state"]], [], [], []
    images = [obs["image"]] if "image" in obs else None
    done = False
    while not done:
        # A copy: some experts edit the observation they are given (MetaWorld's door-open and
        # door-close shift the handle position in place), which would change the recorded state.
        clean = np.asarray(expert.act({k: np.copy(v) for k, v in obs.items()}), dtype=np.float64)
        noisy = clean + noise_rng.normal(0.0, action_noise, size=clean.shape) if action_noise > 0 else clean
        executed = np.clip(noisy, -1.0, 1.0).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(executed[None])
        observations.append(obs["state"])
        if images is not None:
            images.append(obs["image"])
        actions.append(np.clip(clean, -1.0, 1.0).astype(np.float32) if dart else executed)
        rewards.append(reward)
        successes.append(info["success"])
        done = terminated or truncated
    return DemoEpisode(
        task=task,
        instruction=instruction,
        observations=np.stack(observations).astype(np.float32),
        actions=np.stack(actions),
        rewards=np.asarray(rewards, dtype=np.float32),
        successes=np.asarray(successes, dtype=bool),
        success=bool(successes[-1]),
        seed=seed,
        images=None if images is None else np.stack(images),
    )


def load_demos(path: str | Path, simulator=None, cameras: Sequence[str] = (), image_size: int = 64
               ) -> list[DemoEpisode]:
    """Loads every episode listed in `path/manifest.json`, in manifest order; without a manifest,
    the demonstrations in `simulator`'s own format(s) there (e.g. LIBERO's HDF5 files), with the
    views of `cameras` at `image_size` (a manifest's episodes carry the views they were recorded with)."""
    path = Path(path)
    manifest_path = path / "manifest.json"
    if not manifest_path.is_file() and simulator is not None and simulator.has_dataset(path):
        return simulator.load_dataset(path, cameras, image_size)
    if not manifest_path.is_file():
        raise FileNotFoundError(
            f"no demonstrations at {path}: run `stepnft demos --demos.path {path}` first"
        )
    regenerate = (f"delete the folder (`rm -r {path}`) and generate them again (`stepnft train` and `stepnft sft` do "
                  "so themselves), or point --demos.path at another folder")
    try:
        manifest = json.loads(manifest_path.read_text())
        if manifest.get("format") != FORMAT or manifest.get("version") != VERSION:
            raise ValueError(f"expected format {FORMAT!r} version {VERSION}")
        generator = manifest.get("generator", {})
        # An early manifest records no widths: the given simulator's, else any.
        dims = (generator.get("state_dim", getattr(simulator, "state_dim", None)),
                generator.get("action_dim", getattr(simulator, "action_dim", None)))
        views = (len(generator["cameras"]), generator["image_size"]) if generator.get("cameras") else None
        return [_load_episode(path, entry, dims, views) for entry in manifest["episodes"]]
    except FileNotFoundError as e:
        raise FileNotFoundError(
            f"demonstrations at {path} are incomplete ({e}); {regenerate}"
        ) from None
    except (ValueError, KeyError, TypeError, AttributeError, OSError, EOFError, zipfile.BadZipFile) as e:
        # Bad JSON is a ValueError; a damaged or truncated .npz raises any of the others.
        raise ValueError(
            f"corrupt demonstrations at {path} ({type(e).__name__}: {e}); {regenerate}"
        ) from None


def load_or_generate_demos(demos_cfg, env_cfg, simulator, log: Callable[[str], None] = print) -> list[DemoEpisode]:
    """The demonstrations SFT learns from, for a ``DemoConfig`` and an ``EnvConfig``: the first
    ``demos_cfg.count(task)`` (successful, with ``demos_cfg.successful_only``) episodes of every
    task of ``env_cfg``, grouped by task in its order. They come from ``demos_cfg.path``: a
    stepnft demonstrations folder (generated there first if the folder holds none, at the env's
    cameras and image size) or a dataset in the simulator's own format."""
    path = Path(demos_cfg.path)
    tasks = simulator.validate_tasks(env_cfg.tasks)
    check_task_episodes(demos_cfg, simulator)
    cameras, image_size = list(env_cfg.cameras), env_cfg.image_size
    has_manifest = (path / "manifest.json").is_file()
    own_dataset = not has_manifest and simulator.has_dataset(path)  # read at the env's cameras and size
    if not has_manifest and not own_dataset:
        count = max(demos_cfg.count(t) for t in tasks)
        log(f"generating {count} demonstrations per task into {path}")
        generate_demos(tasks, count, path, seed=demos_cfg.seed, action_noise=demos_cfg.action_noise,
                       dart=demos_cfg.dart, max_episode_steps=env_cfg.max_episode_steps, simulator=simulator,
                       max_attempts=demos_cfg.max_attempts, successful_only=demos_cfg.successful_only,
                       cameras=cameras, image_size=image_size)
    elif has_manifest:
        _say_if_recorded_by_other_code(path, log)
    if cameras and not own_dataset and demo_cameras(path) != (cameras, image_size):
        recorded, size = demo_cameras(path)
        raise ValueError(f"demonstrations in {path} were recorded with cameras {recorded} at {size} px, the env "
                         f"renders {cameras} at {image_size} px: point --demos.path at a new folder to record them")
    episodes = [e for e in load_demos(path, simulator, cameras, image_size)
                if e.task in tasks and (e.success or not demos_cfg.successful_only)]
    per_task = {t: [e for e in episodes if e.task == t][: demos_cfg.count(t)] for t in tasks}
    short = [t for t, kept in per_task.items() if len(kept) < demos_cfg.count(t)]
    if short:
        raise ValueError(f"demonstrations in {path} have too few {'successful ' * demos_cfg.successful_only}episodes "
                         f"of {short}: point --demos.path at a new folder (the run generates enough there), or delete "
                         f"this one (`rm -r {path}`)")
    return [e for kept in per_task.values() for e in kept]


RECORDER = ("stepnft/envs", "stepnft/data/demos.py")
"""The code a demonstration depends on: the simulators' experts and envs, and the recorder."""


def _say_if_recorded_by_other_code(path: Path, log: Callable[[str], None]) -> None:
    """One line when the demonstrations in ``path`` were recorded by code whose experts, envs or
    recorder differ from the code running now (or by code of unknown version): the same seed may
    then give other demonstrations, and another SFT start, on a fresh checkout."""
    try:
        manifest = json.loads((path / "manifest.json").read_text())
    except (OSError, ValueError):  # a corrupt manifest is load_demos's to report, with its hint
        return
    generator = manifest.get("generator") if isinstance(manifest, dict) else None
    code = generator.get("code") if isinstance(generator, dict) else None
    recorded = code.get("commit") if isinstance(code, dict) else None
    changed = changed_since(recorded, RECORDER)
    if changed is None and code_commit() is not None:
        log(f"reusing demonstrations in {path} recorded by code of {'unknown version' if not recorded else recorded}: "
            f"delete the folder to record them with this code")
    elif changed:
        log(f"reusing demonstrations in {path} recorded at commit {recorded}; the recorder or experts have changed "
            f"since ({', '.join(changed[:3])}{', ...' if len(changed) > 3 else ''}): delete the folder to record "
            f"them with this code")


def check_task_episodes(demos_cfg, simulator) -> None:
    """``demos_cfg.task_episodes`` may name only tasks of ``simulator`` (a typo is refused); a
    known task the run does not play is ignored, so one config's counts serve any task subset."""
    valid = simulator.task_names()
    unknown = [t for t in demos_cfg.task_episodes if t not in valid]
    if unknown:
        raise ValueError(f"--demos.task-episodes names {', '.join(unknown)}, not a {simulator.label} task: "
                         f"give counts for tasks among {', '.join(valid)}")


def demo_cameras(path: str | Path) -> tuple[list[str], int | None]:
    """The cameras (names, in view order) and image size the demonstrations at ``path`` were
    recorded with (``[], None`` without images)."""
    generator = json.loads((Path(path) / "manifest.json").read_text()).get("generator", {})
    return list(generator.get("cameras", [])), generator.get("image_size")


def _load_episode(root: Path, entry: dict, dims: tuple[int | None, int | None], views: tuple[int, int] | None
                  ) -> DemoEpisode:
    file = root / entry["file"]
    if not file.is_file():
        raise FileNotFoundError(f"missing {entry['file']}")
    keys = ("observations", "actions", "rewards", "successes") + (("images",) if views else ())
    with np.load(file) as data:
        arrays = {key: data[key] for key in keys}
    length = entry["length"]
    expected = {
        "observations": (length + 1, dims[0]),
        "actions": (length, dims[1]),
        "rewards": (length,),
        "successes": (length,),
    }
    if views:
        expected["images"] = (length + 1, views[0], 3, views[1], views[1])
    for key, shape in expected.items():
        found = arrays[key].shape
        if len(found) != len(shape) or any(want is not None and want != n for want, n in zip(shape, found)):
            raise ValueError(
                f"{entry['file']}: {key} has shape {found}, expected {shape}"
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
        images=arrays["images"].astype(np.uint8) if views else None,
    )


def demos_to_chunks(
    episodes: Sequence[DemoEpisode],
    tasks: Sequence[str],
    horizon: int,
    only_successful: bool = True,
    state_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    images: bool = False,
) -> dict[str, torch.Tensor]:
    """The SFT dataset: one sample per time step t of every (successful) episode.

    Returns N samples:
        obs      {"state": float32 [N, S] observations[t] (through `state_fn`, e.g. the
                  proprioceptive part, if given),
                  "task": int64 [N] index of the episode's task in `tasks`,
                  "image": uint8 [N, V, 3, H, W] images[t], with `images`}
        actions  float32 [N, H, A]  actions[t : t+H], past the episode's end repeating its
                                    last action
        mask     bool    [N, H]     False on those repeated (padded) positions
    """
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    task_index = {task: i for i, task in enumerate(tasks)}
    states, task_ids, chunks, masks, views = [], [], [], [], []
    for episode in episodes:
        if only_successful and not episode.success:
            continue
        if episode.task not in task_index:
            raise ValueError(f"demonstration task {episode.task!r} is not in tasks {list(tasks)}")
        if images and episode.images is None:
            raise ValueError(f"a {episode.task} demonstration has no camera images: generate demonstrations with "
                             "--env.cameras set (into a new --demos.path)")
        length = len(episode.actions)
        # steps[t, h] = t + h: the action index each chunk position would take.
        steps = np.arange(length)[:, None] + np.arange(horizon)[None, :]
        states.append(episode.observations[:length] if state_fn is None else state_fn(episode.observations[:length]))
        if images:
            views.append(episode.images[:length])
        task_ids.append(np.full(length, task_index[episode.task], dtype=np.int64))
        chunks.append(episode.actions[np.minimum(steps, length - 1)])
        masks.append(steps < length)
    if not states:
        kind = "successful " if only_successful else ""
        raise ValueError(f"no {kind}demonstrations to build chunks from")
    obs = {"state": torch.from_numpy(np.concatenate(states).astype(np.float32)),
           "task": torch.from_numpy(np.concatenate(task_ids))}
    if images:
        obs["image"] = torch.from_numpy(np.concatenate(views))
    return {
        "obs": obs,
        "actions": torch.from_numpy(np.concatenate(chunks).astype(np.float32)),
        "mask": torch.from_numpy(np.concatenate(masks)),
    }
