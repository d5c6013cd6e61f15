"""A tiny SmolVLA fine-tuned on MetaWorld camera observations: SFT on demonstrations, then
π-StepNFT through `stepnft train --init`, beside the MLP flow policy on the same tasks and budget.

Run in the LeRobot environment (docs/lerobot.md):

    MUJOCO_GL=egl .venv-lerobot/bin/python benchmarks/vla_learning.py --out benchmarks/results/vla

Camera observations (MetaWorld rendering an ``image`` observation, demonstrations holding
images) are being built separately. Until they land, this script uses a stand-in registered only
in this process: ``metaworld-camera``, MetaWorld's chunk env (full 39-d state) plus an ``image``
observation uint8 [1, 3, S, S] of the ``corner2`` camera, rendered once per policy call through
``MetaWorldChunkEnv(render_size=...)``; the demonstrations' images are rendered by replaying
each demonstration from its seed (the replayed states are checked against the recorded ones).
SFT runs ``stepnft.algos.sft.sft_train`` (what `stepnft sft` runs) on those chunks; RL and both
evaluations are the CLI's `stepnft train --init SFT_POLICY --env.name metaworld-camera ...`.

Once camera observations are merged: drop the stand-in and run the same two steps as commands,
`stepnft sft --init TINY --env.cameras corner2 ...` then `stepnft train --init RUN/policy
--env.cameras corner2 ...` (the SmolVLA processor already reads the ``image`` key, uint8
[B, V, 3, H, W], in the order of its image features).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

os.environ.setdefault("MUJOCO_GL", "egl")

from stepnft.envs import SIMULATORS, SimulatorInfo  # noqa: E402
from stepnft.envs.metaworld import MetaWorld, MetaWorldChunkEnv  # noqa: E402

STANDIN = "metaworld-camera"


class CameraChunkEnv(gym.Wrapper):
    """A MetaWorld chunk env with an ``image`` observation rendered once per call (reset, step)."""

    image_size = 64

    def __init__(self, env: MetaWorldChunkEnv):
        super().__init__(env)
        s = self.image_size
        self.observation_space = gym.spaces.Dict({**env.observation_space.spaces,
                                                  "image": gym.spaces.Box(0, 255, (1, 3, s, s), np.uint8)})
        self._image = np.zeros((1, 3, s, s), dtype=np.uint8)

    def _frame(self) -> np.ndarray:
        return np.ascontiguousarray(self.env.render().transpose(2, 0, 1)[None])

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        idle = bool((kwargs.get("options") or {}).get("idle"))
        self._image = np.zeros_like(self._image) if idle else self._frame()
        return obs | {"image": self._image}, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if info["steps"]:  # a finished episode's no-op step renders nothing
            self._image = self._frame()
        return obs | {"image": self._image}, reward, terminated, truncated, info


class CameraMetaWorld(MetaWorld):
    """The stand-in simulator: MetaWorld plus a corner2 camera image per policy call."""

    name = STANDIN
    label = "MetaWorld (camera stand-in)"

    def make_env(self, task, n_exec=1, max_episode_steps=200, terminate_on_success=True, seed=0, render_size=None):
        size = (CameraChunkEnv.image_size,) * 2
        return CameraChunkEnv(MetaWorldChunkEnv(task, n_exec=n_exec, max_episode_steps=max_episode_steps,
                                                terminate_on_success=terminate_on_success, seed=seed, render_size=size))


def register_standin() -> None:
    SIMULATORS[STANDIN] = SimulatorInfo(f"{__name__}:CameraMetaWorld", SIMULATORS["metaworld"].max_episode_steps,
                                        SIMULATORS["metaworld"].default_tasks)


def demo_images(episodes, max_episode_steps: int) -> list[np.ndarray]:
    """``[T, 1, 3, S, S]`` uint8 per demonstration: the camera at each of its states, by replay."""
    sim, out = CameraMetaWorld(), []
    for episode in episodes:
        env = sim.make_env(episode.task, n_exec=1, max_episode_steps=max_episode_steps)
        obs, _ = env.reset(seed=episode.seed)
        frames = [obs["image"]]
        for t, action in enumerate(episode.actions[:-1]):
            obs, *_ = env.step(action[None])
            frames.append(obs["image"])
            if not np.allclose(obs["state"], episode.observations[t + 1], atol=1e-4):
                raise RuntimeError(f"replay of a {episode.task} demonstration diverged at step {t + 1}")
        out.append(np.stack(frames))
        env.close()
    return out


def cli(argv: list) -> None:
    from stepnft.cli import main

    code = main([str(a) for a in argv])
    if code != 0:
        raise SystemExit(f"`stepnft {' '.join(map(str, argv))}` failed with exit code {code}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="benchmarks/results/vla")
    parser.add_argument("--tasks", nargs="+", default=["reach-v3", "drawer-open-v3", "handle-press-v3"])
    parser.add_argument("--demos", type=int, default=5, help="demonstrations per task")
    parser.add_argument("--sft-steps", type=int, default=1500)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--episodes", type=int, default=12, help="episodes per RL iteration")
    parser.add_argument("--eval-episodes", type=int, default=20, help="test episodes per task")
    parser.add_argument("--max-episode-steps", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sft-train", default="expert", choices=["expert", "expert+state", "vlm"],
                        help="parameters SFT trains (a new tiny model's VLM and state projection are random: "
                             "expert+state or vlm give SFT more to fit with); RL trains --rl-train")
    parser.add_argument("--rl-train", default="expert", choices=["expert", "expert+state", "vlm"])
    args = parser.parse_args()

    from stepnft.algos.sft import SFTConfig, sft_train
    from stepnft.data.demos import demos_to_chunks, generate_demos, load_demos
    from stepnft.envs.metaworld import instruction_for
    from stepnft.policies.base import load_policy
    from stepnft.policies.lerobot.tiny import NewSmolVLA, new_smolvla

    register_standin()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    times: dict[str, float] = {}
    common = ["--env.tasks", *args.tasks, "--env.envs-per-task", max(1, args.episodes // len(args.tasks)),
              "--env.max-episode-steps", args.max_episode_steps, "--iterations", args.iterations,
              "--episodes-per-iteration", args.episodes, "--eval.episodes", args.eval_episodes,
              "--eval.every", max(1, args.iterations // 2), "--eval.during-episodes", 10, "--seed", args.seed,
              "--demos.path", out / "demos", "--demos.episodes", args.demos, "--algo.minibatch-size", 128]

    t0 = time.perf_counter()
    if not (out / "demos" / "manifest.json").is_file():
        generate_demos(args.tasks, args.demos, out / "demos", seed=args.seed, max_episode_steps=args.max_episode_steps)
    episodes = [e for e in load_demos(out / "demos") if e.task in args.tasks and e.success]
    images = demo_images(episodes, args.max_episode_steps)
    times["demos_s"] = time.perf_counter() - t0

    # SmolVLA: a new tiny one, SFT on the camera demonstrations (kept in OUT/smolvla_sft and
    # reused by later runs into the same OUT), then π-StepNFT from the CLI.
    t0 = time.perf_counter()
    torch.set_num_threads(1)
    report_path = out / "report.json"
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    if not (out / "smolvla_sft" / "config.json").is_file():
        tiny = out / "tiny_smolvla"
        if not tiny.is_dir():
            new_smolvla(NewSmolVLA(out=str(tiny), cameras=["corner2"], image_size=CameraChunkEnv.image_size,
                                   seed=args.seed, train=args.sft_train))
        policy = load_policy(tiny)
        data = demos_to_chunks(episodes, args.tasks, policy.config.horizon)
        data["obs"]["image"] = torch.from_numpy(np.concatenate([im[: len(e.actions)]
                                                                for im, e in zip(images, episodes)]))
        policy.processor.fit(data["obs"]["state"])
        policy.processor.bind_instructions([instruction_for(t) for t in args.tasks])
        losses = sft_train(policy, data, SFTConfig(steps=args.sft_steps, batch_size=64, lr=1e-3, time_law="beta"),
                           torch.Generator().manual_seed(args.seed))
        policy.config = dataclasses.replace(policy.config, train=args.rl_train)  # what `train --init` trains
        policy.save_pretrained(out / "smolvla_sft")
        times["smolvla_sft_s"] = time.perf_counter() - t0
        report["smolvla_sft"] = {"chunks": len(data["actions"]), "loss_first_50": float(np.mean(losses[:50])),
                                 "loss_last_50": float(np.mean(losses[-50:])), "args": vars(args)}
    runs = {f"smolvla_it{args.iterations}": ["--init", out / "smolvla_sft", "--env.name", STANDIN],
            # The MLP flow policy (state only) on the same tasks, demonstrations and RL budget.
            f"mlp_it{args.iterations}": ["--sft.steps", 3000]}
    for name, flags in runs.items():
        t0 = time.perf_counter()
        cli(["train", "--run-dir", out / name, *flags, *common])
        times[f"{name}_s"] = time.perf_counter() - t0

    report.setdefault("times_s", {}).update(times)
    for name in runs:
        summary = json.loads((out / name / "summary.json").read_text())
        report[name] = {t: {k: summary["tasks"][t][k]["success"] for k in ("before", "after", "best")}
                        for t in args.tasks} | {"average": summary["average"], "env_steps": summary["env_steps"],
                                                "args": vars(args)}
    report_path.write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
