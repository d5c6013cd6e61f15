"""How well few-shot SFT fits LIBERO's scripted demonstrations (docs/libero.md, "Why SFT fails").

For each saved flow policy: the mean absolute error of the first action of its ODE chunk
against the demonstrations' action, per action dimension, on the demonstrations it was trained
on (episodes 0-4 of each task file) and on held-out ones (5-9). Beside it, a plain MLP
regression (state -> action, 2 x 256, 3,000 Adam steps, MSE) on the same training episodes, for
three observations: the 64-d full state, the proprioception with the object of interest (15-d)
and the proprioception alone (8-d), with the state standard deviation floored at 1e-3 and at
the flow policy's 0.05. ``--reference RUN DEMOS`` adds, for scale, the same error of a MetaWorld
SFT policy (``RUN/sft_policy`` of a ``benchmarks/learning.py`` run, whose SFT succeeds) on its own
demonstrations (``DEMOS``, the run's ``demos_seed<s>``). Prints and writes ``fit.md`` and
``fit.json`` under ``--out``.

    MUJOCO_GL=egl python -m stepnft.envs.libero.scripted --tasks $TASKS --episodes 10 --out /tmp/lib/demos10
    MUJOCO_GL=egl python -m stepnft.cli sft --config configs/libero_state.yaml --demos.path /tmp/lib/demos10 \\
        --sft.steps 20000 --eval.episodes 3 --run-dir /tmp/lib/sft20k   # (and the variants in the docs)
    MUJOCO_GL=egl python benchmarks/libero_sft_fit.py --demos /tmp/lib/demos10 --policies /tmp/lib/sft20k/policy ...
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from provenance import command, commit, cpu  # noqa: E402

DIMS = ("x", "y", "z", "rx", "ry", "rz", "grip")


def first_action_errors(policy, episodes, tasks: list[str]) -> np.ndarray:
    """|first action of the policy's ODE chunk - the demonstrator's action| at every step of
    ``episodes``, [steps, A]; the policy is bound to ``tasks``' instructions, in order."""
    errors = []
    for d in episodes:
        obs = torch.as_tensor(d.observations[:-1][:, :policy.config.state_dim])
        raw = {"state": obs, "task": torch.full((len(obs),), tasks.index(d.task))}
        sample = policy.sample(policy.prepare(raw), noise_level=0.0, generator=torch.Generator().manual_seed(0))
        errors.append(np.abs(sample.actions[:, 0].numpy() - d.actions))
    return np.concatenate(errors)


def setting(policy) -> str:
    return f"state {policy.config.state_dim}-d, horizon {policy.config.horizon}, n_exec {policy.config.n_exec}"


def policy_error(policy_dir: Path, episodes_by_task: dict, tasks: list[str]) -> dict:
    from stepnft.envs.libero.suites import all_tasks
    from stepnft.policies.base import Policy

    policy = Policy.from_pretrained(policy_dir)
    policy.eval()
    policy.processor.bind_instructions([all_tasks()[t].instruction for t in tasks], cache_dir=policy_dir.parent / "lang_cache")
    out = {}
    for split, part in (("train", slice(0, 5)), ("held-out", slice(5, 10))):
        episodes = [d for task in tasks for d in episodes_by_task[task][part]]
        out[split] = first_action_errors(policy, episodes, tasks).mean(0).round(3).tolist()
    out["setting"] = setting(policy)
    return out


def reference_error(run: Path, demos_dir: Path) -> dict:
    """First-action error of a MetaWorld run's SFT policy on the demonstrations it was trained on."""
    from stepnft.data.demos import load_demos
    from stepnft.envs import get_simulator
    from stepnft.policies.base import Policy

    import yaml

    tasks = yaml.safe_load((run / "config.yaml").read_text())["env"]["tasks"]
    sim = get_simulator("metaworld")
    policy = Policy.from_pretrained(run / "sft_policy")
    policy.eval()
    policy.processor.bind_instructions([sim.instruction(t) for t in tasks], cache_dir=run / "lang_cache")
    episodes = load_demos(demos_dir)
    errors = first_action_errors(policy, episodes, tasks)
    actions = np.abs(np.concatenate([d.actions for d in episodes]))
    return {"train": errors.mean(0).round(3).tolist(), "mean_abs_action": actions.mean(0).round(3).tolist(),
            "setting": f"MetaWorld {', '.join(tasks)}; {setting(policy)}; actions x y z grip"}


def regression_error(episodes_by_task: dict, tasks: list[str], columns: slice, floor: float, seed: int = 0) -> dict:
    torch.manual_seed(seed)
    train = [d for t in tasks for d in episodes_by_task[t][:5]]
    test = [d for t in tasks for d in episodes_by_task[t][5:10]]
    task_of = {t: k for k, t in enumerate(tasks)}

    def xy(ds):
        x = np.concatenate([np.concatenate([d.observations[:-1][:, columns],
                                            np.eye(len(tasks))[[task_of[d.task]] * len(d.actions)]], 1) for d in ds])
        return torch.as_tensor(x, dtype=torch.float32), torch.as_tensor(np.concatenate([d.actions for d in ds]))

    (xtr, ytr), (xte, yte) = xy(train), xy(test)
    mu, sd = xtr.mean(0), xtr.std(0).clamp(min=floor)
    net = torch.nn.Sequential(torch.nn.Linear(xtr.shape[1], 256), torch.nn.GELU(), torch.nn.Linear(256, 256),
                              torch.nn.GELU(), torch.nn.Linear(256, ytr.shape[1]))
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    for _ in range(3000):
        idx = torch.randint(len(xtr), (256,))
        loss = (net((xtr[idx] - mu) / sd) - ytr[idx]).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        return {split: (net((x - mu) / sd) - y).abs().mean(0).numpy().round(3).tolist()
                for split, x, y in (("train", xtr, ytr), ("held-out", xte, yte))}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--demos", required=True, help="LIBERO HDF5 demonstrations, >= 10 per task (the scripted recorder's)")
    p.add_argument("--policies", nargs="*", default=[], help="saved SFT policies (RUN/policy) trained on episodes 0-4")
    p.add_argument("--reference", nargs=2, metavar=("RUN", "DEMOS"), default=None,
                   help="a MetaWorld benchmarks/learning.py run folder and its demonstrations, for scale")
    p.add_argument("--out", default="benchmarks/results/libero_sft_fit")
    args = p.parse_args()
    torch.set_num_threads(1)
    from stepnft.envs.libero.datasets import load_hdf5

    episodes = load_hdf5(Path(args.demos))
    tasks = sorted({d.task for d in episodes})
    by_task = {t: sorted((d for d in episodes if d.task == t), key=lambda d: d.seed) for t in tasks}
    rows = []
    mean_abs = np.abs(np.concatenate([d.actions for d in episodes])).mean(0).round(3).tolist()
    for policy in args.policies:
        rows.append({"model": f"flow policy {policy}", **policy_error(Path(policy), by_task, tasks)})
    for name, columns in (("full 64-d", slice(0, 64)), ("proprio + object of interest 15-d", slice(0, 15)),
                          ("proprio 8-d", slice(0, 8))):
        for floor in (1e-3, 0.05):
            rows.append({"model": f"MLP regression, {name}, std floor {floor:g}",
                         **regression_error(by_task, tasks, columns, floor)})
    if args.reference:
        rows.append({"model": f"MetaWorld SFT policy {args.reference[0]} (reference)",
                     **reference_error(Path(args.reference[0]), Path(args.reference[1]))})
    lines = ["| model | train: first-action MAE (" + " ".join(DIMS) + ") | held-out |", "|---|---|---|",
             f"| (mean absolute action) | {' '.join(f'{v:.2f}' for v in mean_abs)} | |"]
    for r in rows:
        model = r["model"] + (f" ({r['setting']})" if "setting" in r else "")
        held_out = " ".join(f"{v:.3f}" for v in r["held-out"]) if "held-out" in r else \
            "(mean absolute action " + " ".join(f"{v:.2f}" for v in r["mean_abs_action"]) + ")"
        lines.append(f"| {model} | {' '.join(f'{v:.3f}' for v in r['train'])} | {held_out} |")
    text = "\n".join(lines) + f"\n\nTasks: {', '.join(tasks)}.\n\nCommand: `{command()}` (commit {commit()}).\n"
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fit.md").write_text(text)
    (out / "fit.json").write_text(json.dumps({"command": command(), "commit": commit(), "cpu": cpu(), "rows": rows,
                                              "mean_abs_action": mean_abs}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
