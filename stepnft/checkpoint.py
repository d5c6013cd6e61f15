"""Training checkpoints: policy, EMA policy, optimiser, RNG states, counters; atomic writes.

Layout: ``RUN/checkpoints/iter_000010/{policy/, ema/, optimizer.safetensors, state.json}`` and
``RUN/checkpoints/LATEST`` naming the newest one. A checkpoint is written to a temporary
folder and renamed into place; ``LATEST`` is replaced atomically afterwards, so a kill at any
moment leaves the previous checkpoint intact and pointed to. Nothing is pickled.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from stepnft.policies.flow import FlowPolicy

KEEP = 2  # checkpoints kept on disk


def write_atomic(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` so readers see the old or the new file, never half."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _flatten_optimizer(optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict]:
    sd = optimizer.state_dict()
    tensors, scalars = {}, {}
    for idx, state in sd["state"].items():
        for key, value in state.items():
            if torch.is_tensor(value):
                tensors[f"state.{idx}.{key}"] = value.detach().contiguous().cpu()
            else:
                scalars[f"{idx}.{key}"] = value
    return tensors, {"param_groups": sd["param_groups"], "scalars": scalars}


def _unflatten_optimizer(tensors: dict[str, torch.Tensor], meta: dict) -> dict:
    state: dict[int, dict] = {}
    for name, value in tensors.items():
        _, idx, key = name.split(".", 2)
        state.setdefault(int(idx), {})[key] = value
    for name, value in meta["scalars"].items():
        idx, key = name.split(".", 1)
        state.setdefault(int(idx), {})[key] = value
    return {"state": state, "param_groups": meta["param_groups"]}


def save_checkpoint(run_dir: Path, iteration: int, policy: FlowPolicy, ema: FlowPolicy,
                    optimizer: torch.optim.Optimizer, state: dict, rng: dict[str, torch.Tensor]) -> Path:
    """Write checkpoint ``iter_{iteration}`` atomically and point ``LATEST`` at it."""
    root = run_dir / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    for stale in root.glob(".tmp-*"):  # left by a writer that was killed
        shutil.rmtree(stale, ignore_errors=True)
    name = f"iter_{iteration:06d}"
    tmp = Path(tempfile.mkdtemp(dir=root, prefix=".tmp-"))
    try:
        policy.save_pretrained(tmp / "policy")
        ema.save_pretrained(tmp / "ema")
        tensors, meta = _flatten_optimizer(optimizer)
        save_file({**tensors, **{f"rng.{k}": v for k, v in rng.items()}}, str(tmp / "optimizer.safetensors"))
        (tmp / "state.json").write_text(json.dumps({**state, "iteration": iteration, "optimizer": meta}))
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


def load_checkpoint(run_dir: Path, optimizer_factory) -> dict:
    """Load the newest checkpoint of ``run_dir``.

    ``optimizer_factory(policy) -> optimizer`` builds the optimiser before its state is loaded.
    Returns ``policy``, ``ema``, ``optimizer``, ``state`` (counters, env RNG, ...), ``rng``.
    Raises ValueError with one actionable line if there is none or it is corrupt.
    """
    root = Path(run_dir) / "checkpoints"
    latest = root / "LATEST"
    if not latest.is_file():
        raise ValueError(f"no checkpoint to resume in {run_dir}: start a new run with `stepnft train --run-dir ...`")
    ckpt = root / latest.read_text().strip()
    try:
        policy = FlowPolicy.from_pretrained(ckpt / "policy")
        ema = FlowPolicy.from_pretrained(ckpt / "ema")
        state = json.loads((ckpt / "state.json").read_text())
        tensors = load_file(str(ckpt / "optimizer.safetensors"))
        optimizer = optimizer_factory(policy)
        opt_tensors = {k: v for k, v in tensors.items() if k.startswith("state.")}
        optimizer.load_state_dict(_unflatten_optimizer(opt_tensors, state.pop("optimizer")))
    except (FileNotFoundError, ValueError, KeyError, OSError, SafetensorError, json.JSONDecodeError) as err:
        raise ValueError(f"checkpoint {ckpt} is corrupt or incomplete ({str(err).splitlines()[0]}); "
                         "delete it and point LATEST at an older one, or start a new run") from err
    for p in ema.parameters():
        p.requires_grad_(False)
    rng = {k[len("rng."):]: v for k, v in tensors.items() if k.startswith("rng.")}
    return {"policy": policy, "ema": ema, "optimizer": optimizer, "state": state, "rng": rng, "path": ckpt}
