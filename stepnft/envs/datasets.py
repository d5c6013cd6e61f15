"""Demonstrations of any env from disk: a LeRobot dataset folder, or robomimic-style HDF5.

The readers ``env.name: gym`` uses (``GymSimulator.load_dataset``), for the formats users have
demonstrations in. Both become :class:`~stepnft.envs.episodes.DemoEpisode` objects: states as
the policy sees them, actions mapped from the env's units to the policy's [-1, 1] (the env's
``ActionMap``), each episode's task found by its instruction, camera frames resized to the
env's ``image_size``. A demonstration of T actions gets T + 1 observations (the last repeated).

**LeRobot** (``meta/info.json`` with ``codebase_version`` v2.x or v3.0, frames in
``data/**/*.parquet``, tasks in ``meta/tasks.jsonl`` or ``meta/tasks.parquet``): columns
``observation.state`` (or ``state``), ``action`` (or ``actions``), ``episode_index``,
``frame_index``, ``task_index``; ``next.success`` where recorded (else the last frame of an
episode is its success: LeRobot's datasets hold successful demonstrations); camera ``c`` from
``observation.images.c`` (or ``observation.image`` with one camera), embedded PNG/JPEG bytes
(LeRobot's ``image`` feature; ``video`` features are not decoded).

**HDF5** (robomimic's layout, one or more ``*.hdf5`` files)::

    data.attrs["task"] (optional; else the file name without _demo, else the only task)
    data/demo_<k>/actions       float [T, A]
    data/demo_<k>/obs/state     float [T, S]  (or one dataset per env.state_keys entry, a/b nested)
    data/demo_<k>/obs/<camera>  uint8 [T, H, W, 3]
    data/demo_<k>/dones         [T] (optional: success at the last step otherwise)
"""

from __future__ import annotations

import importlib.util
import io
import json
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from stepnft.envs.episodes import DemoEpisode

HDF5_SUFFIXES = (".hdf5", ".h5")
STATE_COLUMNS = ("observation.state", "state")
ACTION_COLUMNS = ("action", "actions")


def dataset_format(path) -> str | None:
    """``"lerobot"``, ``"hdf5"`` or None: which demonstration format ``path`` holds."""
    path = Path(path)
    if (path / "meta" / "info.json").is_file():
        return "lerobot"
    if path.is_file() and path.suffix in HDF5_SUFFIXES:
        return "hdf5"
    if path.is_dir() and any(p.suffix in HDF5_SUFFIXES for p in path.rglob("*")):
        return "hdf5"
    return None


def resized(frame: np.ndarray, height: int, width: int) -> np.ndarray:
    """A uint8 [H, W, 3] frame at ``height`` x ``width`` (bilinear; unchanged when it has that size)."""
    if frame.shape[:2] == (height, width):
        return frame
    from PIL import Image

    return np.asarray(Image.fromarray(frame).resize((width, height), Image.BILINEAR))


def views(frames: list[np.ndarray], size: int) -> np.ndarray | None:
    """Per-camera frames uint8 [T, H, W, 3] -> the env's ``image`` layout [T, V, 3, size, size]."""
    if not frames:
        return None
    return np.stack([np.stack([resized(f, size, size) for f in camera]) for camera in frames],
                    axis=1).transpose(0, 1, 4, 2, 3)


def decode_image(cell) -> np.ndarray:
    """A LeRobot ``image`` cell (``{"bytes", "path"}``) as uint8 [H, W, 3]."""
    from PIL import Image

    if cell.get("bytes") is None:
        raise ValueError(f"image stored by path only ({cell.get('path')}): images must be embedded in the parquet files")
    return np.asarray(Image.open(io.BytesIO(cell["bytes"])).convert("RGB"))


def lerobot_tasks(root: Path) -> dict[int, str]:
    """A LeRobot dataset's task_index -> instruction."""
    if (root / "meta" / "tasks.jsonl").is_file():
        rows = [json.loads(line) for line in (root / "meta" / "tasks.jsonl").read_text().splitlines() if line.strip()]
        return {int(r["task_index"]): r["task"] for r in rows}
    import pyarrow.parquet as pq

    table = pq.read_table(root / "meta" / "tasks.parquet").to_pydict()
    # v3.0 keeps the instruction as the (pandas) index column, named "task" or "__index_level_0__".
    text = table.get("task") or table.get("__index_level_0__")
    return {int(i): t for i, t in zip(table["task_index"], text)}


def read_lerobot(root: Path) -> tuple[dict, dict]:
    """A LeRobot dataset's ``meta/info.json`` and all its frames as columns (name -> values),
    after the version check."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    info = json.loads((root / "meta" / "info.json").read_text())
    version = str(info.get("codebase_version", ""))
    if not version.startswith(("v2", "v3")):
        raise ValueError(f"{root}: LeRobot dataset version {version or '?'} is not read (v2.x and v3.0 are)")
    files = sorted((root / "data").rglob("*.parquet"))
    if not files:
        raise FileNotFoundError(f"{root}: no parquet files under data/")
    return info, pa.concat_tables([pq.read_table(f) for f in files]).to_pydict()


def lerobot_image_columns(root: Path, info: dict, columns: dict, cameras: Sequence[tuple[str, Sequence[str]]]
                          ) -> list[str]:
    """The image column of each ``(camera, candidate column names)``: the first candidate the
    dataset has, embedded images (video features are refused: they are not decoded)."""
    features = info.get("features", {})
    found_columns = []
    for camera, names in cameras:
        found = [n for n in names if n in features or n in columns]
        if found and features.get(found[0], {}).get("dtype") == "video":
            raise ValueError(f"{root}: {found[0]} is stored as video, which is not decoded: use it without cameras")
        if not found or found[0] not in columns:
            raise ValueError(f"{root} has no {camera} images (tried {', '.join(names)})")
        found_columns.append(found[0])
    return found_columns


def lerobot_episodes(columns: dict):
    """``(episode_index, rows)`` for every episode, its rows in frame order."""
    episode_ids = np.asarray(columns["episode_index"])
    order = np.lexsort((np.asarray(columns["frame_index"]), episode_ids))
    for episode in np.unique(episode_ids):
        yield int(episode), order[episode_ids[order] == episode]


def instruction_key(text: str) -> str:
    """An instruction as episodes are matched to tasks by it: case, spacing and a final period ignored."""
    return " ".join(str(text).lower().strip().rstrip(".").split())


class _Tasks:
    """Finds a demonstration's task among the simulator's by instruction or name."""

    def __init__(self, sim):
        self.names = sim.task_names()
        self.by_text = {instruction_key(t): t for t in self.names}
        self.by_text |= {instruction_key(sim.instruction(t)): t for t in self.names}
        self.instruction = sim.instruction

    def find(self, text: str | None, where: str) -> str:
        if text is not None and instruction_key(text) in self.by_text:
            return self.by_text[instruction_key(text)]
        if len(self.names) == 1:
            return self.names[0]  # one task: every demonstration is its
        raise ValueError(f"{where}: task {text!r} matches no task's name or instruction ({', '.join(self.names)}): "
                         "set env.instructions to the dataset's wording")


def _episode(tasks: _Tasks, task: str, state, actions, successes, seed: int, images, state_dim: int,
             where: str) -> DemoEpisode:
    state, actions = np.asarray(state, dtype=np.float32), np.asarray(actions, dtype=np.float32)
    if len(actions) == 0 or len(state) != len(actions):
        raise ValueError(f"{where}: a demonstration has {len(actions)} actions and {len(state)} observations")
    if state.shape[1] != state_dim:
        raise ValueError(f"{where}: states have {state.shape[1]} values, the env's state {state_dim} (env.state_keys)")
    successes = np.maximum.accumulate(np.asarray(successes, dtype=bool))
    return DemoEpisode(
        task=task, instruction=tasks.instruction(task), observations=np.concatenate([state, state[-1:]]),
        actions=actions, rewards=successes.astype(np.float32), successes=successes, success=bool(successes[-1]),
        seed=seed, images=None if images is None else np.ascontiguousarray(np.concatenate([images, images[-1:]])))


def load_dataset(path, sim, action_maps, cameras: Sequence[str] = (), image_size: int = 64,
                 state_keys: Sequence[str] = ()) -> list[DemoEpisode]:
    """Every demonstration at ``path`` for simulator ``sim`` (its tasks and state size), actions
    mapped by ``action_maps[task]`` (each task's :class:`~stepnft.envs.gym.ActionMap`); an HDF5
    file without ``obs/state`` has one dataset per ``state_keys`` entry."""
    path = Path(path)
    kind = dataset_format(path)
    if kind is None:
        raise FileNotFoundError(f"no demonstrations at {path}: expected a LeRobot dataset folder (meta/info.json) "
                                "or *.hdf5 files")
    reader = "pyarrow" if kind == "lerobot" else "h5py"
    if importlib.util.find_spec(reader) is None:
        raise ValueError(f"reading {path} needs {reader}: pip install \"stepnft[datasets]\"")
    try:
        if kind == "lerobot":
            return _load_lerobot(path, _Tasks(sim), sim.state_dim, action_maps, list(cameras), image_size)
        return _load_hdf5(path, _Tasks(sim), sim.state_dim, action_maps, list(cameras), image_size, list(state_keys))
    except (KeyError, TypeError, IndexError) as err:  # a file in another layout
        raise ValueError(f"{path} is not a {kind} dataset this reads ({type(err).__name__}: {err}); docs/gym.md "
                         "describes the layout") from err


def pick_column(columns, names: Sequence[str], what: str) -> str:
    """The first of ``names`` among ``columns``; a KeyError naming them otherwise."""
    for name in names:
        if name in columns:
            return name
    raise KeyError(f"no {what} column (tried {', '.join(names)})")


def _load_lerobot(root: Path, tasks: _Tasks, state_dim: int, action_maps, cameras: list[str], image_size: int):
    info, columns = read_lerobot(root)
    state_key = pick_column(columns, STATE_COLUMNS, "state")
    action_key = pick_column(columns, ACTION_COLUMNS, "action")
    image_columns = lerobot_image_columns(root, info, columns, [
        (c, [f"observation.images.{c.replace('/', '.')}", *(["observation.image"] if len(cameras) == 1 else [])])
        for c in cameras])
    has_tasks = any((root / "meta" / f).is_file() for f in ("tasks.jsonl", "tasks.parquet"))
    instructions = lerobot_tasks(root) if has_tasks else {}
    episodes = []
    for episode, rows in lerobot_episodes(columns):
        text = instructions.get(int(columns["task_index"][rows[0]])) if "task_index" in columns else None
        task = tasks.find(text, f"{root} episode {episode}")
        state = [columns[state_key][i] for i in rows]
        acts = action_maps[task].to_policy(np.asarray([columns[action_key][i] for i in rows], dtype=np.float64))
        frames = [np.stack([decode_image(columns[col][i]) for i in rows]) for col in image_columns]
        successes = ([bool(columns["next.success"][i]) for i in rows] if "next.success" in columns
                     else np.arange(len(rows)) == len(rows) - 1)
        episodes.append(_episode(tasks, task, state, acts, successes, episode, views(frames, image_size),
                                 state_dim, str(root)))
    return episodes


def _load_hdf5(path: Path, tasks: _Tasks, state_dim: int, action_maps, cameras: list[str], image_size: int,
               state_keys: list[str]):
    import h5py

    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.suffix in HDF5_SUFFIXES)
    episodes = []
    for file in files:
        with h5py.File(file, "r") as f:
            data = f["data"]
            label = data.attrs.get("task")
            label = label.decode() if isinstance(label, bytes) else label
            task = tasks.find(label or re.sub(r"_demo$", "", file.stem), str(file))
            for key in sorted(data, key=lambda k: int(k.rsplit("_", 1)[-1])):
                demo = data[key]
                obs = demo["obs"]
                keys = ["state"] if "state" in obs else list(state_keys)
                if not keys:
                    raise KeyError(f"{file}/{key}/obs has no 'state' dataset (or give env.state_keys)")
                state = np.concatenate([obs[k][()].reshape(len(obs[k]), -1) for k in keys], axis=1)
                acts = action_maps[task].to_policy(demo["actions"][()])
                successes = demo["dones"][()] if "dones" in demo else np.arange(len(acts)) == len(acts) - 1
                frames = [obs[c][()] for c in cameras]
                episodes.append(_episode(tasks, task, state, acts, successes, int(key.rsplit("_", 1)[-1]),
                                         views(frames, image_size), state_dim, str(file)))
    return episodes
