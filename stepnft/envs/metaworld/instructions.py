"""One natural-language instruction per MetaWorld v3 task, for language-conditioned policies.

The wording is ours, written from each task's name and what its success check measures.
This module does not import MetaWorld, so text encoders can use it cheaply;
`tests/envs/test_metaworld.py` checks that its keys match MetaWorld's task list exactly.
"""

INSTRUCTIONS: dict[str, str] = {
    "assembly-v3": "pick up the nut and fit it onto the peg",
    "basketball-v3": "pick up the ball and dunk it into the basket",
    "bin-picking-v3": "pick up the cube and move it from one bin into the other bin",
    "box-close-v3": "pick up the lid and put it on the box to close it",
    "button-press-topdown-v3": "press the button down from above",
    "button-press-topdown-wall-v3": "press the button down from above, next to the wall",
    "button-press-v3": "push the button in from the front",
    "button-press-wall-v3": "reach around the wall and push the button in",
    "coffee-button-v3": "press the button on the coffee machine",
    "coffee-pull-v3": "pull the mug out from under the coffee machine",
    "coffee-push-v3": "push the mug under the coffee machine",
    "dial-turn-v3": "turn the dial",
    "disassemble-v3": "pick the nut up off the peg",
    "door-close-v3": "push the door closed",
    "door-lock-v3": "turn the lock to lock the door",
    "door-open-v3": "pull the door open by its handle",
    "door-unlock-v3": "turn the lock to unlock the door",
    "drawer-close-v3": "push the drawer closed",
    "drawer-open-v3": "pull the drawer open",
    "faucet-close-v3": "turn the faucet handle to close the faucet",
    "faucet-open-v3": "turn the faucet handle to open the faucet",
    "hammer-v3": "pick up the hammer and drive the nail into the wall",
    "hand-insert-v3": "pick up the block and put it into the hole",
    "handle-press-side-v3": "press the handle down from the side",
    "handle-press-v3": "press the handle down",
    "handle-pull-side-v3": "pull the handle up from the side",
    "handle-pull-v3": "pull the handle up",
    "lever-pull-v3": "pull the lever up",
    "peg-insert-side-v3": "pick up the peg and insert it sideways into the hole",
    "peg-unplug-side-v3": "pull the peg sideways out of the hole",
    "pick-out-of-hole-v3": "pick the peg up out of the hole",
    "pick-place-v3": "pick up the puck and place it at the goal",
    "pick-place-wall-v3": "pick up the puck, lift it over the wall and place it at the goal",
    "plate-slide-back-side-v3": "slide the plate sideways back out of the cabinet",
    "plate-slide-back-v3": "slide the plate back out of the cabinet",
    "plate-slide-side-v3": "slide the plate sideways into the cabinet",
    "plate-slide-v3": "slide the plate forward into the cabinet",
    "push-back-v3": "pull the puck back towards the robot to the goal",
    "push-v3": "push the puck to the goal",
    "push-wall-v3": "push the puck around the wall to the goal",
    "reach-v3": "move the gripper to the goal position",
    "reach-wall-v3": "move the gripper over the wall to the goal position",
    "shelf-place-v3": "pick up the puck and place it on the shelf",
    "soccer-v3": "push the ball into the soccer goal",
    "stick-pull-v3": "grasp the stick and use it to pull the thermos to the goal",
    "stick-push-v3": "grasp the stick and use it to push the thermos to the goal",
    "sweep-into-v3": "sweep the puck into the hole",
    "sweep-v3": "sweep the puck off the edge of the table",
    "window-close-v3": "slide the window closed",
    "window-open-v3": "slide the window open",
}


def unknown_task_error(task: str, valid: list[str]) -> ValueError:
    """The one-line error for a task name MetaWorld does not have."""
    return ValueError(f"unknown MetaWorld task {task!r}; valid names: {', '.join(valid)}")


def instruction_for(task: str) -> str:
    """The instruction for a MetaWorld v3 task name, e.g. 'pick-place-v3'."""
    if task not in INSTRUCTIONS:
        raise unknown_task_error(task, sorted(INSTRUCTIONS))
    return INSTRUCTIONS[task]
