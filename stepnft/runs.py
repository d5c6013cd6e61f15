"""The run folder: atomic writes, the metric logger, learning-curve plots, summaries.

A run folder holds ``config.yaml`` (reproduces the run), ``metrics.jsonl`` (one strict-JSON
record per line), TensorBoard logs (``tb/``), ``checkpoints/``, ``sft_policy/``, ``policy/``,
``learning_curve.png`` and ``summary.json``.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path


def write_atomic(path: str | Path, data: str | bytes) -> None:
    """Replace ``path`` with ``data`` so readers see the old or the new file, never half."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def prepare_run_dir(path: str | Path, must_exist: bool = False, flag: str = "--run-dir") -> Path:
    """Create ``path`` and check it is writable; ValueError with one line (naming the option
    ``flag`` that chose it) otherwise."""
    run_dir = Path(path)
    if must_exist and not run_dir.is_dir():
        raise ValueError(f"run directory {run_dir} does not exist: nothing to resume")
    created = [d for d in (run_dir, *run_dir.parents) if not d.exists()]
    probe = run_dir / ".write-test"
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        probe.write_text("ok")
        probe.unlink()
    except OSError as err:
        with contextlib.suppress(OSError):  # e.g. a full disk: leave nothing of the probe
            probe.unlink(missing_ok=True)
            for d in created:
                d.rmdir()
        raise ValueError(f"cannot write to {run_dir} ({err.strerror}): choose another {flag}") from err
    return run_dir


LOCK_NAME = ".stepnft.lock"
"""The lock file of a folder while a command writes it (hidden: a folder holding only it counts as empty)."""


class FolderBusy(ValueError):
    """Another live process writes the folder (it holds the folder's lock)."""


@contextlib.contextmanager
def writer_lock(folder: str | Path, name: str = LOCK_NAME) -> Iterator[Path]:
    """Hold the OS file lock (``flock``) of ``folder/name`` for the block: one writer per folder.
    The lock belongs to the open file, so it ends with the process however it ends (kill -9
    included): a stale lock cannot outlive its holder. A folder another process holds is a
    :class:`FolderBusy` (one line naming its PID). The folder is created if missing, and removed
    again if it is left empty; the lock file is removed when the block ends (a lock taken on a
    file that was removed meanwhile is taken again on the new one). Only the process that writes
    takes it: Ray workers and torchrun ranks write nothing of the run."""
    folder = Path(folder)
    created = [d for d in (folder, *folder.parents) if not d.exists()]
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise FolderBusy(f"{folder} is being written by another stepnft process (PID {holder}): wait for it to "
                             "end, or stop it, before writing there") from None
        try:
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)  # its holder removed the file as we took it: take the new one
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield path
    finally:
        with contextlib.suppress(OSError):
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                path.unlink()
        os.close(fd)  # releases the lock
        for d in created:  # nothing was written (bad input, a start that cleaned up): leave nothing behind
            with contextlib.suppress(OSError):
                d.rmdir()


RUN_MARKER = "run.json"
"""Names the kind of run a folder holds (``train`` or ``sft``): a folder belongs to one run."""


def run_kind(run_dir: Path) -> str | None:
    """The kind of run ``run_dir`` holds (``train``, ``sft``), ``other`` for a non-empty folder
    that is no run, or None when it is empty or missing."""
    marker = run_dir / RUN_MARKER
    if marker.is_file():
        try:
            return str(json.loads(marker.read_text())["kind"])
        except (ValueError, KeyError, TypeError):
            return "other"
    if (run_dir / "checkpoints" / "LATEST").is_file():
        return "train"  # written before run markers existed
    if run_dir.is_dir() and any(not p.name.startswith(".") for p in run_dir.iterdir()):
        return "other"
    return None


def check_free(run_dir: Path) -> None:
    """A new run must not overwrite anything: refuse a folder that already holds something."""
    held = run_kind(run_dir)
    checkpoints = run_dir / "checkpoints"
    if held == "train" and ((checkpoints / "LATEST").is_file() or any(checkpoints.glob("iter_*"))):
        raise ValueError(f"{run_dir} already holds a training run: continue it with `stepnft train --resume {run_dir}`, "
                         "or choose another --run-dir")
    if held == "train":
        raise ValueError(f"{run_dir} already holds a training run without a checkpoint to continue from: choose "
                         f"another --run-dir, or delete that one (`rm -r {run_dir}`)")
    if held == "sft":
        raise ValueError(f"{run_dir} already holds an SFT run: start RL from it with `stepnft train --config "
                         f"{run_dir}/config.yaml --init {run_dir}/policy --run-dir NEW_DIR`, or choose another --run-dir")
    if held is not None:
        raise ValueError(f"{run_dir} is not empty: choose another --run-dir (a run folder holds one run only)")


FOLDER_KINDS = {"train": "a training run", "sft": "an SFT run", "demos": "demonstrations",
                "comparison": "a comparison (stepnft compare)", "videos": "videos"}
"""What a folder a command writes into may hold, by :func:`folder_kind`."""


def folder_kind(path: Path) -> str | None:
    """What folder ``path`` holds: a run (``train``, ``sft``: :func:`run_kind`), ``demos`` (a
    demonstrations manifest), ``comparison`` (``compare.json``), ``videos`` (.mp4 files only),
    ``other`` for anything else; None when it is missing or empty (hidden files aside)."""
    kind = run_kind(path)
    if kind != "other":
        return kind
    if (path / "manifest.json").is_file():
        return "demos"
    if (path / "compare.json").is_file():
        return "comparison"
    videos = False
    for file in path.rglob("*"):
        if file.is_file() and not file.name.startswith("."):
            if file.suffix != ".mp4":
                return "other"
            videos = True
    return "videos" if videos else "other"


def check_folder(path: str | Path, kind: str, flag: str) -> Path:
    """The folder a command writes ``kind`` (a key of :data:`FOLDER_KINDS`) into, given by
    option ``flag``: refused, before any work, if it holds anything else; else created and
    checked writable (:func:`prepare_run_dir`)."""
    path = Path(path)
    held = folder_kind(path) if path.is_dir() else None
    if held not in (None, kind):
        what = FOLDER_KINDS.get(held) or "other files (" + ", ".join(sorted(
            p.name for p in path.iterdir() if not p.name.startswith("."))[:3]) + ")"
        raise ValueError(f"{path} holds {what}, not {FOLDER_KINDS[kind]}: choose another {flag} (a new or empty folder)")
    return prepare_run_dir(path, flag=flag)


def mark_run(run_dir: Path, kind: str) -> None:
    """Mark ``run_dir`` as holding a run of ``kind`` (``train`` or ``sft``)."""
    write_atomic(run_dir / RUN_MARKER, json.dumps({"kind": kind}))


RUN_FILES = frozenset({RUN_MARKER, "config.yaml", "metrics.jsonl", "tb", "checkpoints", "sft_policy", "policy",
                       "best_policy", "lang_cache", "videos", "learning_curve.png", "summary.json"})
"""What a ``train`` or ``sft`` run writes at the top of its folder."""


def clear_interrupted_start(run_dir: Path, kind: str) -> bool:
    """Empty ``run_dir`` if it holds a start of a ``kind`` run (``train``, ``sft``) that ended
    before anything could be continued (killed, e.g. kill -9 or a power cut, before a training
    run's first checkpoint or before an SFT run's summary): its files are all stepnft's own and
    nothing of it can resume. True if it did. The caller holds the folder's :func:`writer_lock`,
    so no live process is writing it."""
    if run_kind(run_dir) != kind or (run_dir / "summary.json").is_file():
        return False
    checkpoints = run_dir / "checkpoints"
    if kind == "train" and ((checkpoints / "LATEST").is_file() or any(checkpoints.glob("iter_*"))):
        return False
    if any(p.name not in RUN_FILES and not p.name.startswith(".") for p in run_dir.iterdir()):
        return False  # something a run does not write: the user's, so the folder stays as it is
    for child in run_dir.iterdir():
        if child.name != LOCK_NAME:
            shutil.rmtree(child) if child.is_dir() and not child.is_symlink() else child.unlink()
    return True


def check_resumable(run_dir: Path) -> None:
    """``--resume`` continues training runs only."""
    held = run_kind(run_dir)
    if held != "train":
        what = {"sft": "an SFT run", None: "nothing", "other": "no stepnft run"}.get(held, f"a {held} run")
        raise ValueError(f"cannot resume {run_dir}: it holds {what}, not a training run")


def _finite_or_none(value):
    return value if not isinstance(value, float) or math.isfinite(value) else None


class MetricLogger:
    """Writes each record to ``metrics.jsonl`` (non-finite numbers as null) and TensorBoard."""

    def __init__(self, run_dir: Path, resume_iteration: int | None = None):
        from torch.utils.tensorboard import SummaryWriter

        self.path = run_dir / "metrics.jsonl"
        kept = []
        if resume_iteration is not None and self.path.is_file():
            # Drop records written after the checkpoint we resume from: they will be redone.
            kept = [r for r in read_metrics(self.path, drop_torn_tail=True)
                    if r.get("iteration", 0) <= resume_iteration and not r.get("final")]
        write_atomic(self.path, "".join(json.dumps(r) + "\n" for r in kept))
        # TensorBoard drops the events a killed run wrote past the checkpoint, as above.
        purge_step = max((int(r.get("env_steps", 0)) for r in kept), default=-1) + 1
        self.writer = SummaryWriter(str(run_dir / "tb"), purge_step=purge_step if kept else None)

    def log(self, record: dict) -> None:
        step = int(record.get("env_steps", 0))
        for key, value in record.items():
            if "/" in key and isinstance(value, (int, float)) and math.isfinite(value):
                self.writer.add_scalar(key, value, step)
        with self.path.open("a") as f:
            f.write(json.dumps({k: _finite_or_none(v) for k, v in record.items()}, allow_nan=False) + "\n")
        self.writer.flush()

    def video(self, tag: str, frames: list, fps: float, step: int) -> None:
        """An episode's frames ``[H, W, 3]`` uint8 as an animated GIF in TensorBoard's images
        (every 2nd frame at half size: small event files; the run's mp4 files are full)."""
        import io

        import imageio.v2 as imageio
        from tensorboard.compat.proto.summary_pb2 import Summary

        small = [f[::2, ::2] for f in frames[::2]]
        buffer = io.BytesIO()
        imageio.mimwrite(buffer, small, format="GIF", duration=2000 / fps, loop=0)
        image = Summary.Image(height=small[0].shape[0], width=small[0].shape[1], colorspace=3,
                              encoded_image_string=buffer.getvalue())
        self.writer._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]), step)
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def read_metrics(path: Path, drop_torn_tail: bool = False) -> list[dict]:
    """The records of a ``metrics.jsonl``. A last line cut short (the run was killed while
    writing it) is dropped with a warning when ``drop_torn_tail``; any other bad line is a
    ValueError naming the file."""
    lines = [line for line in Path(path).read_text().splitlines() if line]
    records = []
    for i, line in enumerate(lines):
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as err:
            if drop_torn_tail and i == len(lines) - 1:
                warnings.warn(f"dropped the torn last line of {path} (the run was stopped while writing it)",
                              stacklevel=2)
                break
            raise ValueError(f"{path} line {i + 1} is not valid JSON ({err.msg}): repair or remove that line") from err
    return records


def task_panels(titles: list[str]):
    """A grid of success-rate panels (3 per row), one per title: ``(fig, axes)``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(3, len(titles))
    rows = -(-len(titles) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False, sharex=True)
    for ax, title in zip(axes.flat, titles):
        ax.set_title(title, fontsize=10)
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(titles):]:
        ax.axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("env steps")
    return fig, axes


def save_panels(fig, axes, title: str, path: Path) -> Path:
    """Legend on the first panel, ``title`` on top, saved as ``path``."""
    import matplotlib.pyplot as plt

    if axes.flat[0].get_legend_handles_labels()[0]:  # nothing drawn: no empty legend
        axes.flat[0].legend(loc="lower right", fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_learning_curve(run_dir: Path) -> Path:
    """``learning_curve.png``: success against env steps, the average and one panel per task:
    rollouts (Flow-SDE, acting policy), validation evaluations during training and the test
    evaluations before and after (ODE)."""
    records = read_metrics(run_dir / "metrics.jsonl")
    tasks = sorted({k.split("/", 1)[1] for r in records for k in r if k.startswith(("eval/", "rollout/"))})
    panels = [("average", "charts/rollout_success_rate", "charts/validation_success_rate", "charts/success_rate")]
    panels += [(t, f"rollout/{t}", f"validation/{t}", f"eval/{t}") for t in tasks]
    fig, axes = task_panels([p[0] for p in panels])
    for ax, (_, roll_key, val_key, test_key) in zip(axes.flat, panels):
        for key, style, label in ((roll_key, dict(color="tab:gray", alpha=0.5), "rollout (Flow-SDE)"),
                                  (val_key, dict(color="tab:blue", marker="o", ms=3), "validation (ODE)"),
                                  (test_key, dict(color="tab:red", marker="s", ls="none"), "test (ODE)")):
            points = [(r["env_steps"], r[key]) for r in records if r.get(key) is not None]
            if points:
                ax.plot(*zip(*points), label=label, **style)
    return save_panels(fig, axes, f"stepnft: {run_dir.name}", run_dir / "learning_curve.png")
