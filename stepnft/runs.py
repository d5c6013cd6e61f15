"""The run folder: atomic writes, the metric logger, learning-curve plots, summaries.

A run folder holds ``config.yaml`` (reproduces the run), ``metrics.jsonl`` (one strict-JSON
record per line), TensorBoard logs (``tb/``), ``checkpoints/``, ``sft_policy/``, ``policy/``,
``learning_curve.png`` and ``summary.json``.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
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


def prepare_run_dir(path: str | Path, must_exist: bool = False) -> Path:
    """Create ``path`` and check it is writable; ValueError with one line otherwise."""
    run_dir = Path(path)
    if must_exist and not run_dir.is_dir():
        raise ValueError(f"run directory {run_dir} does not exist: nothing to resume")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        probe = run_dir / ".write-test"
        probe.write_text("ok")
        probe.unlink()
    except OSError as err:
        raise ValueError(f"cannot write to {run_dir} ({err.strerror}): choose another --run-dir") from err
    return run_dir


def refuse_existing_run(run_dir: Path) -> None:
    """A new run must not overwrite another: refuse a folder that already holds one."""
    if (run_dir / "checkpoints" / "LATEST").is_file():
        raise ValueError(f"{run_dir} already holds a run with checkpoints: continue it with "
                         f"`stepnft train --resume {run_dir}`, or choose another --run-dir")
    if (run_dir / "config.yaml").is_file():
        raise ValueError(f"{run_dir} already holds a run (config.yaml): choose another --run-dir")


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
            kept = [r for r in read_metrics(self.path) if r.get("iteration", 0) <= resume_iteration and not r.get("final")]
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


def read_metrics(path: Path) -> list[dict]:
    """The records of a ``metrics.jsonl``."""
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line]


def plot_learning_curve(run_dir: Path) -> Path:
    """``learning_curve.png``: evaluation and rollout success against env steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = read_metrics(run_dir / "metrics.jsonl")
    fig, ax = plt.subplots(figsize=(7, 4))
    roll = [(r["env_steps"], r["charts/rollout_success_rate"]) for r in records
            if r.get("charts/rollout_success_rate") is not None]
    ev = [(r["env_steps"], r["charts/success_rate"]) for r in records if r.get("charts/success_rate") is not None]
    if roll:
        ax.plot(*zip(*roll), color="tab:gray", alpha=0.6, label="rollout (Flow-SDE, acting policy)")
    if ev:
        ax.plot(*zip(*ev), "o-", color="tab:blue", label="evaluation (ODE, fixed states)")
    ax.set_xlabel("env steps")
    ax.set_ylabel("success rate")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    ax.set_title(f"stepnft: {run_dir.name}")
    fig.tight_layout()
    out = run_dir / "learning_curve.png"
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
