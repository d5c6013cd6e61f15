"""Scripted pick-and-place demonstrations for LIBERO-Object, written as LIBERO HDF5 files.

LIBERO ships no scripted experts and its demonstration datasets are downloads. For machines
without them, this records demonstrations of libero_object tasks ("pick up the X and place it
in the basket") with a scripted controller that reads the object and basket positions from the
simulator (privileged information no policy sees): above the object, down, close the gripper,
lift, over the basket, open. Tried from initial states 0-3 of each task, it succeeded on all
four for seven objects (alphabet soup, bbq sauce, tomato sauce, butter, milk, chocolate pudding,
orange juice), on one for the cream cheese and on none for the ketchup and the salad dressing;
failed attempts are discarded. With ``--action-noise s`` the executed translation gets Gaussian
noise of scale ``s`` while the file keeps the controller's own action for the state it was in
(DART: the demonstrations then show how to recover from the small errors a cloned policy
makes, which plain demonstrations never visit). The files are in LIBERO's own format
(``stepnft.envs.libero.datasets``), so SFT reads them exactly as it reads the published ones:

    python -m stepnft.envs.libero.scripted --tasks pick_up_the_alphabet_soup_and_place_it_in_the_basket \\
        --episodes 5 --out demos/libero_scripted
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from stepnft.envs.libero.datasets import HDF5_IMAGE_KEYS, write_hdf5

GRIPPER_OPEN, GRIPPER_CLOSED = -1.0, 1.0
POSITION_GAIN = 40.0
"""Translation action per metre of error (OSC_POSE moves the hand up to 5 cm per unit action)."""


def _plan(obj: np.ndarray, basket: np.ndarray) -> list[tuple[np.ndarray | None, float, int]]:
    """(hand target or None to hold still, gripper command, max steps) for each phase."""
    up = np.array([0.0, 0.0, 1.0])
    return [(obj + 0.12 * up, GRIPPER_OPEN, 40), (obj + 0.01 * up, GRIPPER_OPEN, 40), (None, GRIPPER_CLOSED, 15),
            (obj + 0.25 * up, GRIPPER_CLOSED, 40), (basket + 0.25 * up, GRIPPER_CLOSED, 60),
            (basket + 0.15 * up, GRIPPER_CLOSED, 20), (None, GRIPPER_OPEN, 40)]


def record_episode(env, seed: int, action_noise: float = 0.0, placement: int | None = None) -> dict | None:
    """One scripted episode on a one-action ``LiberoChunkEnv`` of a libero_object task from
    initial state ``seed``: LIBERO's per-step arrays (observations before each action, the
    controller's noise-free actions), or None if it failed. ``action_noise``: scale of the
    Gaussian noise added to the executed translation (drawn from a stream seeded by ``seed``).
    ``placement``: start from LIBERO's random object placement with this seed instead (none of
    the 50 evaluation states)."""
    rng = np.random.default_rng(seed)
    env.reset(seed=seed, options=None if placement is None else {"placement": placement})
    robosuite_env = env._env.env
    obj_name, basket_name = env._env.obj_of_interest[:2]
    raw = robosuite_env._get_observations()
    plan = _plan(raw[f"{obj_name}_pos"].copy(), raw[f"{basket_name}_pos"].copy())
    record = {k: [] for k in ("actions", "states", "ee_pos", "ee_ori", "gripper_states", "joint_states")}
    frames = {HDF5_IMAGE_KEYS[camera]: [] for camera in env._cameras}
    info, terminated, truncated = {"success": False}, False, False
    for target, gripper, max_steps in plan:
        for _ in range(max_steps):
            raw = robosuite_env._get_observations()
            if target is None:
                move = np.zeros(3)
            elif np.linalg.norm(target - raw["robot0_eef_pos"]) < 0.01:
                break
            else:
                move = np.clip(POSITION_GAIN * (target - raw["robot0_eef_pos"]), -1.0, 1.0)
            action = np.concatenate([move, np.zeros(3), [gripper]]).astype(np.float32)
            obs = env._copy_obs()
            state = obs["state"]
            record["states"].append(env.sim_state())
            record["ee_pos"].append(state[:3])
            record["ee_ori"].append(state[3:6])
            record["gripper_states"].append(state[6:])
            record["joint_states"].append(raw["robot0_joint_pos"].astype(np.float32))
            for view, key in zip(obs.get("image", ()), frames):
                # LIBERO's files hold robosuite's raw frames: [H, W, 3], rotated by 180 degrees
                frames[key].append(view.transpose(1, 2, 0)[::-1, ::-1])
            record["actions"].append(action)
            executed = action.copy()
            if action_noise > 0:
                executed[:3] = np.clip(executed[:3] + rng.normal(0.0, action_noise, 3), -1.0, 1.0)
            _, _, terminated, truncated, info = env.step(executed[None])
            if terminated or truncated:
                break
        if terminated or truncated:
            break
    if not info["success"]:
        return None
    out = {k: np.stack(v) for k, v in record.items()}
    return out | {k: np.stack(v) for k, v in frames.items() if v}


def record_demos(task: str, episodes: int, out_dir: str | Path, max_attempts: int | None = None,
                 cameras: tuple[str, ...] = ("agentview", "robot0_eye_in_hand"), image_size: int = 128,
                 action_noise: float = 0.0, first_placement: int | None = None) -> Path:
    """Scripted demonstrations of ``task`` until ``episodes`` succeed (initial states 0, 1, ...,
    or, with ``first_placement`` k, LIBERO's random placements seeded k, k + 1, ...) into
    ``out_dir/<suite>/<task>_demo.hdf5``; returns the file. ``action_noise``: see :func:`record_episode`."""
    if action_noise < 0:
        raise ValueError(f"action_noise is a standard deviation, >= 0; got {action_noise}")
    from stepnft.envs.libero import LIBERO
    from stepnft.envs.libero.suites import all_tasks

    info = all_tasks()[task]
    if info.suite != "libero_object":
        raise ValueError(f"the scripted pick-and-place handles libero_object tasks only, not {task}")
    max_attempts = 5 * episodes if max_attempts is None else max_attempts
    env = LIBERO().make_env(task, n_exec=1, max_episode_steps=info.max_episode_steps, cameras=cameras,
                            image_size=image_size)
    demos, attempts = [], 0
    try:
        while len(demos) < episodes:
            if attempts == max_attempts:
                raise ValueError(f"the scripted pick-and-place succeeded on only {len(demos)} of {attempts} initial "
                                 f"states of {task}: ask for fewer episodes")
            placement = None if first_placement is None else first_placement + attempts
            demo = record_episode(env, attempts, action_noise, placement)
            attempts += 1
            if demo is not None:
                demos.append(demo)
    finally:
        env.close()
    path = Path(out_dir) / info.suite / f"{task}_demo.hdf5"
    write_hdf5(path, task, demos)
    return path


def main(argv: list[str] | None = None) -> int:
    from stepnft.envs.libero import LIBERO

    parser = argparse.ArgumentParser(prog="python -m stepnft.envs.libero.scripted", description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=["libero_object"], help="libero_object tasks (or the suite)")
    parser.add_argument("--episodes", type=int, default=5, help="successful demonstrations per task")
    parser.add_argument("--out", required=True, help="output folder (LIBERO's datasets layout)")
    parser.add_argument("--cameras", nargs="*", default=["agentview", "robot0_eye_in_hand"],
                        help="cameras whose frames are stored (none: no frames)")
    parser.add_argument("--image-size", type=int, default=128, help="side of the stored frames (LIBERO's: 128)")
    parser.add_argument("--action-noise", type=float, default=0.0,
                        help="std of the Gaussian noise on the executed translation; the files keep the noise-free "
                             "actions (DART: demonstrations of recoveries). Default 0: none")
    parser.add_argument("--first-placement", type=int, default=None,
                        help="start from LIBERO's random object placements seeded N, N+1, ... instead of the 50 "
                             "benchmark initial states (keeps demonstrations off the evaluation states)")
    args = parser.parse_args(argv)
    if args.action_noise < 0:
        parser.error(f"--action-noise must be >= 0, got {args.action_noise}")
    for task in LIBERO().validate_tasks(args.tasks):
        try:
            path = record_demos(task, args.episodes, args.out, cameras=tuple(args.cameras), image_size=args.image_size,
                                action_noise=args.action_noise, first_placement=args.first_placement)
            print(f"wrote {path}")
        except ValueError as err:
            print(f"skipped {task}: {err}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
