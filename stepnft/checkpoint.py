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
import re
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
NAME = re.compile(r"iter_\d{6}")
"""A checkpoint's folder name; ``LATEST`` holds one, never a path."""
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


def save_checkpoint(run_dir: Path, iteration: int, policy: Policy, state: dict, config: dict | None = None) -> Path:
    """Write checkpoint ``iter_{iteration}`` (the policy and ``state``) atomically and point
    ``LATEST`` at it. ``config``: the run's settings it was written under (plain values, kept in
    ``state.json``), which ``--resume`` compares with the folder's config.yaml."""
    root = Path(run_dir) / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    for stale in root.glob(".tmp-*"):  # left by a writer that was killed
        shutil.rmtree(stale, ignore_errors=True)
    name = f"iter_{iteration:06d}"
    skeleton, tensors = flatten_state({**state, "iteration": iteration})
    bad = non_finite(tensors)
    if bad:
        raise ValueError(f"refusing to write checkpoint {name} with non-finite values ({len(bad)} tensors)")
    try:
        tmp = Path(tempfile.mkdtemp(dir=root, prefix=".tmp-"))
        try:
            policy.save_pretrained(tmp / "policy")
            save_file(tensors, str(tmp / "state.safetensors"))
            meta = {"format_version": FORMAT_VERSION, "state": skeleton, **({"config": config} if config else {})}
            (tmp / "state.json").write_text(json.dumps(meta))
            final = root / name
            if final.exists():  # never the one LATEST names: iterations only grow after a resume
                shutil.rmtree(final)
            os.replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        write_atomic(root / "LATEST", name)
    except (OSError, SafetensorError) as err:  # e.g. a full disk: say so in one line, keep the previous one
        reason = getattr(err, "strerror", None) or str(err).splitlines()[0]
        kept = (f"the previous checkpoint is intact: free some space, then `stepnft train --resume {run_dir}`"
                if (root / "LATEST").is_file() else "no earlier checkpoint: free some space and start the run again")
        raise OSError(f"could not write checkpoint {name} into {root} ({reason}); {kept}") from err
    for old in sorted(p for p in root.glob("iter_*") if p.name != name)[:-(KEEP - 1) or None]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def load_checkpoint(run_dir: Path) -> dict:
    """Load the newest checkpoint of ``run_dir``: ``{"policy", "state", "path", "config"}``
    (``config``: the settings it was written under, None in checkpoints older than that record).

    Raises ValueError with one actionable line if there is none or it is corrupt.
    """
    root = Path(run_dir) / "checkpoints"
    ckpt = root / latest_name(run_dir)
    try:
        policy = Policy.from_pretrained(ckpt / "policy")
        meta = json.loads((ckpt / "state.json").read_text())
        if not isinstance(meta, dict):
            raise ValueError(f"state.json holds a JSON {type(meta).__name__}, not an object")
        if meta.get("format_version") != FORMAT_VERSION:
            raise ValueError(f"checkpoint format {meta.get('format_version')}, this stepnft reads {FORMAT_VERSION}")
        state = unflatten_state(meta["state"], load_file(str(ckpt / "state.safetensors")))
    except (FileNotFoundError, ValueError, KeyError, TypeError, OSError, SafetensorError, json.JSONDecodeError,
            UnicodeDecodeError) as err:
        older = [p.name for p in _checkpoints(root) if p.name < ckpt.name]
        fix = (f"delete it and point LATEST at the one before (`rm -r {ckpt} && echo {older[-1]} > {root / 'LATEST'}`)"
               if older else f"no older checkpoint is left: start a new run in another --run-dir")
        raise ValueError(f"checkpoint {ckpt} is corrupt or incomplete ({str(err).splitlines()[0]}); {fix}") from err
    config = meta.get("config")
    return {"policy": policy, "state": state, "path": ckpt, "config": config if isinstance(config, dict) else None}


def _checkpoints(root: Path) -> list[Path]:
    """The checkpoint folders under ``root``, oldest first."""
    return sorted(p for p in root.glob("iter_*") if NAME.fullmatch(p.name) and p.is_dir())


def latest_name(run_dir: Path) -> str:
    """The checkpoint ``RUN/checkpoints/LATEST`` names; a ValueError saying how to repair it
    when it is missing or names anything but a checkpoint folder of this run."""
    root = Path(run_dir) / "checkpoints"
    latest = root / "LATEST"
    try:
        name = latest.read_text().strip()[:200] if latest.is_file() else None
    except UnicodeDecodeError:
        name = "(bytes that are not text)"
    if name is not None and NAME.fullmatch(name) and (root / name).is_dir():
        return name
    found = _checkpoints(root)
    problem = ("has no checkpoints/LATEST" if name is None
               else f"has a checkpoints/LATEST that names {name!r}, not a checkpoint folder of this run")
    if not found:
        raise ValueError(f"no checkpoint to resume in {run_dir}: it {problem} and no checkpoint folder (it stopped "
                         "before its first checkpoint); start a new run in another --run-dir, or delete this one")
    raise ValueError(f"cannot resume {run_dir}: it {problem}; point it at its newest checkpoint "
                     f"(`echo {found[-1].name} > {latest}`), then resume")
