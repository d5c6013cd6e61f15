"""LIBERO demonstrations from disk: LIBERO's published HDF5 files and LeRobot-format datasets.

Both become :class:`stepnft.envs.episodes.DemoEpisode` objects for the SFT path (``demos_to_chunks``)
with the env's ``state``: the full 64-d state (proprioception and object poses) where the file
holds the MuJoCo states to read the objects' poses from (LIBERO's HDF5 files do: each state is
set in an env of the task and observed), else the 8-d proprioception (end-effector position,
axis-angle orientation, gripper finger positions; a LeRobot dataset), 7-d actions and the task's instruction as the simulator defines it; with
``cameras`` (``agentview``, ``robot0_eye_in_hand``) also their frames as the env's ``image``,
uint8 [T+1, V, 3, S, S], upright and resized to ``image_size`` S if stored at another size. A
demonstration of T actions gets T + 1 observations: the last one repeated (the files hold one
observation per action).

**LIBERO HDF5** (robomimic-style, one file per task, ``<suite>/<task>_demo.hdf5``)::

    data.attrs: "problem_info" (JSON with "language_instruction"), "bddl_file_name", "env_args", ...
    data/demo_<k>/actions           float [T, 7]
    data/demo_<k>/obs/ee_pos        float [T, 3]    (or ee_states [T, 6]: position + axis-angle)
    data/demo_<k>/obs/ee_ori        float [T, 3]
    data/demo_<k>/obs/gripper_states  float [T, 2]
    data/demo_<k>/obs/agentview_rgb, eye_in_hand_rgb   uint8 [T, H, W, 3] (robosuite's raw frames)
    data/demo_<k>/rewards, dones    [T] (optional: the published files hold only successes)
    data/demo_<k>/states            float [T, D] flattened MuJoCo states (for the objects' poses)

The task is the file's BDDL name (``bddl_file_name`` without ``.bddl``, else the file name
without ``_demo.hdf5``). ``path`` is one file or a folder searched recursively (e.g. LIBERO's
``datasets`` folder with one subfolder per suite).

**LeRobot** (a dataset folder: ``meta/info.json`` with ``codebase_version`` v2.x or v3.0, frames
in ``data/**/*.parquet``, tasks in ``meta/tasks.jsonl`` (v2) or ``meta/tasks.parquet`` (v3)).
Columns read: ``observation.state`` (or ``state``) [8], ``action`` (or ``actions``) [7],
``episode_index``, ``frame_index``, ``task_index``; camera frames from parquet image columns
``observation.images.image`` / ``observation.images.wrist_image`` (or ``image`` /
``wrist_image``) for agentview / robot0_eye_in_hand, stored as encoded PNG/JPEG bytes (LeRobot's
``image`` feature type). Videos (the ``video`` feature type) are not decoded: use such a dataset
without cameras. The episode's
task is found by its instruction (the benchmark's or the BDDL file's wording; case and a final
period ignored); its instruction then is the benchmark's, like every LIBERO episode here.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from stepnft.envs.datasets import HDF5_SUFFIXES, dataset_format
from stepnft.envs.datasets import decode_image as _decode
from stepnft.envs.datasets import instruction_key as _instruction_key
from stepnft.envs.datasets import lerobot_episodes, lerobot_image_columns, read_lerobot
from stepnft.envs.datasets import lerobot_tasks as _lerobot_tasks
from stepnft.envs.datasets import pick_column as _pick
from stepnft.envs.datasets import views as _views
from stepnft.envs.episodes import DemoEpisode
from stepnft.envs.libero.suites import all_tasks

LEROBOT_STATE_KEYS = ("observation.state", "state")
LEROBOT_ACTION_KEYS = ("action", "actions")
HDF5_IMAGE_KEYS = {"agentview": "agentview_rgb", "robot0_eye_in_hand": "eye_in_hand_rgb"}
LEROBOT_IMAGE_KEYS = {"agentview": ("observation.images.image", "image"),
                      "robot0_eye_in_hand": ("observation.images.wrist_image", "wrist_image")}


def load_dataset(path: Path, cameras: Sequence[str] = (), image_size: int = 64) -> list[DemoEpisode]:
    """Every demonstration at ``path`` (either format), file by file, demo by demo; with the
    frames of ``cameras`` at ``image_size``."""
    unknown = [c for c in cameras if c not in HDF5_IMAGE_KEYS]
    if unknown:
        raise ValueError(f"unknown LIBERO camera {unknown[0]!r}; its cameras: {', '.join(HDF5_IMAGE_KEYS)}")
    kind = dataset_format(path)
    if kind is None:
        raise FileNotFoundError(f"no LIBERO demonstrations at {path}: expected *.hdf5 files or a LeRobot dataset "
                                "(meta/info.json); docs/libero.md says where to get them")
    try:
        load = load_hdf5 if kind == "hdf5" else load_lerobot
        return load(path, list(cameras), image_size)
    except (KeyError, TypeError, IndexError) as err:  # a file in another layout
        raise ValueError(f"{path} is not a LIBERO {kind} dataset ({type(err).__name__}: {err}); "
                         "docs/libero.md describes the layout read") from err


def _episode(task: str, state: np.ndarray, actions: np.ndarray, successes: np.ndarray, seed: int,
             images: np.ndarray | None) -> DemoEpisode:
    if len(actions) == 0 or len(state) != len(actions):
        raise ValueError(f"a demonstration of {task} has {len(actions)} actions and {len(state)} observations")
    successes = np.maximum.accumulate(np.asarray(successes, dtype=bool))
    return DemoEpisode(
        task=task, instruction=all_tasks()[task].instruction,
        observations=np.concatenate([state, state[-1:]]).astype(np.float32),
        actions=np.asarray(actions, dtype=np.float32), rewards=successes.astype(np.float32),
        successes=successes, success=bool(successes[-1]), seed=seed,
        images=None if images is None else np.ascontiguousarray(np.concatenate([images, images[-1:]])))


# ----------------------------------------------------------------------------- LIBERO HDF5

def load_hdf5(path: Path, cameras: Sequence[str] = (), image_size: int = 64) -> list[DemoEpisode]:
    """The demonstrations of one LIBERO HDF5 file, or of every such file under a folder."""
    import h5py

    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.suffix in HDF5_SUFFIXES)
    episodes = []
    env = None
    for file in files:
        with h5py.File(file, "r") as f:
            data = f["data"]
            bddl = data.attrs.get("bddl_file_name")
            bddl = bddl.decode() if isinstance(bddl, bytes) else bddl
            task = Path(bddl).stem if bddl else re.sub(r"_demo$", "", file.stem)
            if task not in all_tasks():
                raise ValueError(f"{file}: {task!r} is not a task of LIBERO's suites")
            for key in sorted(data, key=lambda k: int(k.rsplit("_", 1)[-1])):
                demo = data[key]
                obs = demo["obs"]
                pose = obs["ee_states"][()] if "ee_states" in obs else np.concatenate([obs["ee_pos"], obs["ee_ori"]], 1)
                state = np.concatenate([pose, obs["gripper_states"]], axis=1)
                if "states" in demo:  # the objects' poses, observed in the recorded MuJoCo states
                    if env is None or env.task.name != task:
                        if env is not None:
                            env.close()
                        from stepnft.envs.libero.env import LiberoChunkEnv

                        env = LiberoChunkEnv(task)
                    sim_states = demo["states"][()]
                    # States of another model layout (another LIBERO version) cannot be set: the
                    # demonstration then keeps the proprioception alone, which a full-state run
                    # refuses with its hint (LIBERO.policy_state).
                    if sim_states.ndim == 2 and sim_states.shape[1] == env.sim_state().size:
                        state = np.concatenate([state, env.full_states(sim_states)[:, len(state[0]):]], axis=1)
                actions = demo["actions"][()]
                # The published files hold only successful demonstrations.
                successes = demo["dones"][()] if "dones" in demo else np.arange(len(actions)) == len(actions) - 1
                # robosuite's raw frames are rotated by 180 degrees; the env's are upright
                frames = [obs[HDF5_IMAGE_KEYS[c]][()][:, ::-1, ::-1] for c in cameras]
                episodes.append(_episode(task, state, actions, successes, int(key.rsplit("_", 1)[-1]),
                                         _views(frames, image_size)))
    if env is not None:
        env.close()
    return episodes


def write_hdf5(path: Path, task: str, demos: list[dict[str, np.ndarray]]) -> None:
    """Write demonstrations of ``task`` as one LIBERO HDF5 file (the layout in the module doc).

    Each demo maps LIBERO's per-step keys to arrays of T rows: ``actions``, ``states`` and the
    observations ``ee_pos``, ``ee_ori``, ``gripper_states``, ``joint_states`` and, if present,
    ``agentview_rgb`` / ``eye_in_hand_rgb`` (robosuite's raw frames); ``ee_states``, rewards and
    dones (1 on the last step) are derived as LIBERO's own dataset script does.
    """
    import h5py

    info = all_tasks()[task]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with h5py.File(tmp, "w") as f:
        data = f.create_group("data")
        data.attrs["problem_info"] = json.dumps({"problem_name": "libero", "domain_name": "robosuite",
                                                 "language_instruction": info.instruction})
        data.attrs["bddl_file_name"] = info.bddl_file
        data.attrs["env_name"] = "libero"
        data.attrs["env_args"] = json.dumps({"type": 1, "env_name": "libero", "bddl_file": info.bddl_file,
                                             "env_kwargs": {"control_freq": 20, "camera_heights": 128,
                                                            "camera_widths": 128}})
        data.attrs["macros_image_convention"] = "opengl"
        for k, demo in enumerate(demos):
            group = data.create_group(f"demo_{k}")
            length = len(demo["actions"])
            obs = group.create_group("obs")
            for key in ("ee_pos", "ee_ori", "gripper_states", "joint_states", "agentview_rgb", "eye_in_hand_rgb"):
                if key in demo:
                    obs.create_dataset(key, data=demo[key])
            obs.create_dataset("ee_states", data=np.concatenate([demo["ee_pos"], demo["ee_ori"]], axis=1))
            group.create_dataset("actions", data=demo["actions"])
            group.create_dataset("states", data=demo["states"])
            ends = (np.arange(length) == length - 1).astype(np.uint8)
            group.create_dataset("rewards", data=ends)
            group.create_dataset("dones", data=ends)
            group.attrs["num_samples"] = length
            group.attrs["init_state"] = demo["states"][0]
    tmp.replace(path)


# ----------------------------------------------------------------------------- LeRobot

def load_lerobot(root: Path, cameras: Sequence[str] = (), image_size: int = 64) -> list[DemoEpisode]:
    """The episodes of a LeRobot dataset on disk (module doc: the subset of the format read)."""
    info, columns = read_lerobot(root)
    state_key = _pick(columns, LEROBOT_STATE_KEYS, "state")
    action_key = _pick(columns, LEROBOT_ACTION_KEYS, "action")
    image_columns = lerobot_image_columns(root, info, columns, [(c, LEROBOT_IMAGE_KEYS[c]) for c in cameras])
    by_instruction = {_instruction_key(text): name for name, t in all_tasks().items()
                      for text in (t.bddl_instruction(), t.instruction)}
    instructions = _lerobot_tasks(root)
    episodes = []
    for episode, rows in lerobot_episodes(columns):
        text = instructions[int(columns["task_index"][rows[0]])]
        if _instruction_key(text) not in by_instruction:
            raise ValueError(f"{root}: episode {episode} has instruction {text!r}, which no LIBERO task has")
        task = by_instruction[_instruction_key(text)]
        state = np.asarray([columns[state_key][i] for i in rows], dtype=np.float32)
        actions = np.asarray([columns[action_key][i] for i in rows], dtype=np.float32)
        frames = [np.stack([_decode(columns[col][i]) for i in rows]) for col in image_columns]
        # LeRobot's LIBERO datasets hold successful demonstrations only.
        successes = np.arange(len(rows)) == len(rows) - 1
        episodes.append(_episode(task, state, actions, successes, episode, _views(frames, image_size)))
    return episodes
