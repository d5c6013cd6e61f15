"""Training checkpoints: the policy plus a nested state (algorithm, collector, counters, RNGs).

Layout: ``RUN/checkpoints/iter_000010/{policy/, state.safetensors, state.json}`` and
``RUN/checkpoints/LATEST`` naming the newest one. ``policy/`` is an ordinary saved policy (load
it with ``Policy.from_pretrained``). The state is any tree of dicts, lists, tensors and JSON
values: tensors go to ``state.safetensors``, the rest (with typed dict keys) to ``state.json``.
A checkpoint is written to a temporary folder and renamed into place; ``LATEST`` is replaced
atomically afterwards, so a kill at any moment leaves the previous checkpoint intact and
pointed to. Nothing is pickled.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from stepnft.policies.base import Policy, non_finite
from stepnft.runs import write_atomic

KEEP = 2  # checkpoints kept on disk
FORMAT_VERSION = 3
"""3: training progress in one record, collectors that draw episode plans (runs of format 2 cannot resume)."""


def flatten_state(tree: Any) -> tuple[Any, dict[str, torch.Tensor]]:
    """Split a state tree into a JSON skeleton and its tensors (keyed ``t0``, ``t1``, ...).
    Dicts keep the type of their keys (an optimizer's state is keyed by int)."""
    tensors: dict[str, torch.Tensor] = {}

    def walk(node):
        if torch.is_tensor(node):
            key = f"t{len(tensors)}"
            tensors[key] = node.detach().contiguous().cpu()
            return {"tensor": key}
        if isinstance(node, dict):
            return {"dict": [[k, walk(v)] for k, v in node.items()]}
        if isinstance(node, (list, tuple)):
            return {"list": [walk(v) for v in node]}
        return {"value": node}

    return walk(tree), tensors


def unflatten_state(skeleton: Any, tensors: dict[str, torch.Tensor]) -> Any:
    """Inverse of :func:`flatten_state` (tuples come back as lists)."""
    if "tensor" in skeleton:
        return tensors[skeleton["tensor"]]
    if "dict" in skeleton:
        return {k: unflatten_state(v, tensors) for k, v in skeleton["dict"]}
    if "list" in skeleton:
        return [unflatten_state(v, tensors) for v in skeleton["list"]]
    return skeleton["value"]


def save_checkpoint(run_dir: Path, iteration: int, policy: Policy, state: dict) -> Path:
    """Write checkpoint ``iter_{iteration}`` (the policy and ``state``) atomically and point
    ``LATEST`` at it."""
    root = Path(run_dir) / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    for stale in root.glob(".tmp-*"):  # left by a writer that was killed
        shutil.rmtree(stale, ignore_errors=True)
    name = f"iter_{iteration:06d}"
    skeleton, tensors = flatten_state({**state, "iteration": iteration})
    bad = non_finite(tensors)
    if bad:
        raise ValueError(f"refusing to write checkpoint {name} with non-finite values ({len(bad)} tensors)")
    tmp = Path(tempfile.mkdtemp(dir=root, prefix=".tmp-"))
    try:
        policy.save_pretrained(tmp / "policy")
        save_file(tensors, str(tmp / "state.safetensors"))
        (tmp / "state.json").write_text(json.dumps({"format_version": FORMAT_VERSION, "state": skeleton}))
        final = root / name
        if final.exists():  # never the one LATEST names: iterations only grow after a resume
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    write_atomic(root / "LATEST", name)
    for old in sorted(p for p in root.glob("iter_*") if p.name != name)[:-(KEEP - 1) or None]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def load_checkpoint(run_dir: Path) -> dict:
    """Load the newest checkpoint of ``run_dir``: ``{"policy", "state", "path"}``.

    Raises ValueError with one actionable line if there is none or it is corrupt.
    """
    root = Path(run_dir) / "checkpoints"
    latest = root / "LATEST"
    if not latest.is_file():
        raise ValueError(f"no checkpoint to resume in {run_dir}: start a new run with `stepnft train --run-dir ...`")
    ckpt = root / latest.read_text().strip()
    try:
        policy = Policy.from_pretrained(ckpt / "policy")
        meta = json.loads((ckpt / "state.json").read_text())
        if meta.get("format_version") != FORMAT_VERSION:
            raise ValueError(f"checkpoint format {meta.get('format_version')}, this stepnft reads {FORMAT_VERSION}")
        state = unflatten_state(meta["state"], load_file(str(ckpt / "state.safetensors")))
    except (FileNotFoundError, ValueError, KeyError, TypeError, OSError, SafetensorError, json.JSONDecodeError) as err:
        raise ValueError(f"checkpoint {ckpt} is corrupt or incomplete ({str(err).splitlines()[0]}); "
                         "delete it and point LATEST at an older one, or start a new run") from err
    return {"policy": policy, "state": state, "path": ckpt}
