"""The ManiSkill3 tasks stepnft offers, their instructions, and where things are in their states.

Only tasks whose assets ship inside the mani-skill wheel (procedural objects on ManiSkill's
table scene, a Panda arm with 7-d end-effector actions): YCB objects, PartNet-Mobility and
ReplicaCAD need downloads (``python -m mani_skill.utils.download_asset``) and are left out.
PushT-v1 is left out too: its stick robot has 6-d actions.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TaskInfo:
    """One task as stepnft sees it."""

    instruction: str
    """The natural-language instruction (ManiSkill has none; written here from the task's docstring)."""
    max_episode_steps: int
    """ManiSkill's own episode cap for the task (its registration's ``max_episode_steps``)."""


TASKS: dict[str, TaskInfo] = {
    "PickCube-v1": TaskInfo("pick up the red cube and move it to the green goal point", 50),
    "PushCube-v1": TaskInfo("push the blue cube into the red and white target region", 50),
    "PullCube-v1": TaskInfo("pull the blue cube back into the red and white target region", 50),
    "StackCube-v1": TaskInfo("stack the red cube on the green cube", 50),
    "LiftPegUpright-v1": TaskInfo("lift the peg lying on the table to stand upright", 50),
    "PegInsertionSide-v1": TaskInfo("insert the peg into the hole in the box from the side", 100),
    "PlugCharger-v1": TaskInfo("plug the charger into the receptacle", 200),
    "PokeCube-v1": TaskInfo("use the peg to push the red cube to the goal", 50),
    "PlaceSphere-v1": TaskInfo("place the blue sphere into the bin", 50),
    "RollBall-v1": TaskInfo("push the blue ball so that it rolls into the goal region", 80),
    "PullCubeTool-v1": TaskInfo("use the L-shaped tool to pull the cube closer", 100),
    "StackPyramid-v1": TaskInfo("stack the three cubes into a pyramid", 250),
}
"""Tasks by ManiSkill's environment id."""

STATE_DIM = 64
"""Every task's state is padded with zeros to this size (StackPyramid-v1's 64 values, the
largest), so one multi-task policy and vector env take them all."""


def _layout(*fields: tuple[str, int]) -> dict[str, slice]:
    """Slices of named fields laid out one after another from index 18 (after the arm's qpos 9
    and qvel 9, ManiSkill's ``agent`` part)."""
    out, start = {"qpos": slice(0, 9), "qvel": slice(9, 18)}, 18
    for name, size in fields:
        out[name] = slice(start, start + size)
        start += size
    return out


# ManiSkill's ``obs_mode="state"`` flattens ``agent`` (qpos, qvel) then the task's
# ``_get_obs_extra`` dict, in the order that method builds it (poses: position xyz, quaternion wxyz).
# tests/envs/test_maniskill.py checks these against the simulator's own objects.
STATE_LAYOUTS: dict[str, dict[str, slice]] = {
    "PickCube-v1": _layout(("is_grasped", 1), ("tcp_pose", 7), ("goal_pos", 3), ("obj_pose", 7),
                           ("tcp_to_obj_pos", 3), ("obj_to_goal_pos", 3)),
    "PushCube-v1": _layout(("tcp_pose", 7), ("goal_pos", 3), ("obj_pose", 7)),
    "PullCube-v1": _layout(("tcp_pose", 7), ("goal_pos", 3), ("obj_pose", 7)),
    "StackCube-v1": _layout(("tcp_pose", 7), ("cubeA_pose", 7), ("cubeB_pose", 7), ("tcp_to_cubeA_pos", 3),
                            ("tcp_to_cubeB_pos", 3), ("cubeA_to_cubeB_pos", 3)),
}
"""Named slices of the state of the tasks that have scripted experts."""
