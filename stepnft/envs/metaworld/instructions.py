"""One natural-language instruction per MetaWorld v3 task, for language-conditioned policies.

The wording is ours, written from each task's name and what its success check measures.
This module does not import MetaWorld, so text encoders can use it cheaply;
`tests/envs/test_metaworld.py` checks that its keys match MetaWorld's task list exactly.

``PARAPHRASES`` rewords every instruction in plain words, as a new user might: ``train``
variants for training randomisation (``env.randomize semantic``) and ``heldout`` variants for
the semantic suite, never used in training (the tests check the lists are disjoint and differ
from every canonical instruction). The five default tasks have 4 training and 8 held-out
variants, the others 2 and 4.
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


PARAPHRASES: dict[str, dict[str, tuple[str, ...]]] = {
    # --- the five default tasks -----------------------------------------------------------------
    "reach-v3": {
        "train": ("move the hand to the goal", "reach for the target position", "bring the gripper to the target",
                  "go to the goal spot with the gripper"),
        "heldout": ("put your hand where the marker is", "touch the target point in the air",
                    "send the robot's fingers over to the goal", "position the end effector at the target",
                    "get the claw to the marked location", "travel with the gripper until it reaches the goal",
                    "move your arm so the hand ends up on the target", "reach out to the marked point"),
    },
    "push-v3": {
        "train": ("push the puck to the target", "slide the puck over to the goal", "shove the puck to the goal spot",
                  "move the puck to the goal by pushing it"),
        "heldout": ("nudge the disc until it sits on the marker", "push the little round block onto the target",
                    "slide the hockey puck across the table to the goal",
                    "without lifting it, move the puck to the target", "bump the puck along to the marked spot",
                    "drive the puck over to where the goal is", "give the puck a push so it ends on the goal",
                    "use the gripper to shove the disc to the target"),
    },
    "pick-place-v3": {
        "train": ("grab the puck and put it at the goal", "pick the puck up and place it on the target",
                  "lift the puck and set it down at the goal", "take the puck and move it to the goal"),
        "heldout": ("grasp the disc, carry it and drop it at the marker", "lift the round block over to the target",
                    "pick up the hockey puck and bring it to the goal spot",
                    "hold the puck in the gripper and move it to the target point",
                    "raise the puck off the table and deliver it to the goal", "carry the puck to the marked location",
                    "get the puck into your hand and put it where the goal is",
                    "fetch the puck and leave it at the target"),
    },
    "door-open-v3": {
        "train": ("open the door by pulling its handle", "pull the handle to swing the door open",
                  "swing the door open", "grab the door handle and open it"),
        "heldout": ("get that door open", "yank the door handle so the door swings wide",
                    "the door is closed, open it up", "hook the handle and drag the door open",
                    "make the door swing out towards you", "pull on the door until it is open",
                    "use the handle to open the cabinet door", "open up the little door on the box"),
    },
    "drawer-open-v3": {
        "train": ("open the drawer", "pull out the drawer", "slide the drawer open", "drag the drawer open by its handle"),
        "heldout": ("get the drawer out", "pull the drawer towards you until it is open",
                    "grab the drawer handle and pull", "the drawer is shut, open it",
                    "draw the drawer out of the cabinet", "slide out the drawer of the nightstand",
                    "tug the drawer open", "make the drawer come out"),
    },
    # --- the other tasks ------------------------------------------------------------------------
    "assembly-v3": {
        "train": ("put the nut onto the peg", "place the ring over the peg"),
        "heldout": ("slide the wrench ring down onto the post", "drop the nut over the peg so it fits",
                    "grab the ring and thread it on the pole", "assemble the nut and the peg"),
    },
    "basketball-v3": {
        "train": ("put the ball in the basket", "dunk the ball into the hoop"),
        "heldout": ("score a basket with the ball", "drop the ball through the hoop",
                    "lift the ball and slam it in the net", "get the ball into the basketball hoop"),
    },
    "bin-picking-v3": {
        "train": ("move the cube into the other bin", "transfer the block between the bins"),
        "heldout": ("carry the little box from the left bin to the right one", "take the cube out and drop it in the second bin",
                    "relocate the block to the empty bin", "pick the cube from its bin and put it in the other one"),
    },
    "box-close-v3": {
        "train": ("close the box with its lid", "put the lid on the box"),
        "heldout": ("cover the box", "lift the top and set it on the box", "shut the box by placing the cover",
                    "place the lid so the box is closed"),
    },
    "button-press-topdown-v3": {
        "train": ("press the button from the top", "push the button downward"),
        "heldout": ("hit the button straight down", "poke the button from above", "push down on the top button",
                    "press down on the button"),
    },
    "button-press-topdown-wall-v3": {
        "train": ("press the button from the top beside the wall", "push the button downward near the wall"),
        "heldout": ("hit the button straight down next to the wall", "poke the button from above by the wall",
                    "push down on the button that sits against the wall", "press down on the button near the wall"),
    },
    "button-press-v3": {
        "train": ("press the button from the front", "push the button in"),
        "heldout": ("poke the button on the front panel", "hit the button straight ahead",
                    "push the front button all the way in", "press the button facing you"),
    },
    "button-press-wall-v3": {
        "train": ("get around the wall and press the button", "push the button behind the wall"),
        "heldout": ("go past the wall to hit the button", "avoid the wall and poke the button",
                    "press the button that is hidden by the wall", "reach past the barrier and push the button"),
    },
    "coffee-button-v3": {
        "train": ("push the coffee machine button", "press the button to make coffee"),
        "heldout": ("start the coffee maker", "hit the switch on the espresso machine",
                    "turn on the coffee machine with its button", "poke the coffee maker's button"),
    },
    "coffee-pull-v3": {
        "train": ("pull the mug away from the coffee machine", "take the mug out from the coffee machine"),
        "heldout": ("slide the cup out from under the coffee maker", "drag the mug back towards you",
                    "remove the cup from the espresso machine", "get the mug out of the coffee maker"),
    },
    "coffee-push-v3": {
        "train": ("push the mug into the coffee machine", "slide the mug under the coffee machine"),
        "heldout": ("put the cup under the coffee maker's spout", "shove the mug in place below the machine",
                    "slide the cup under the espresso machine", "get the mug under the coffee maker"),
    },
    "dial-turn-v3": {
        "train": ("rotate the dial", "spin the dial"),
        "heldout": ("twist the knob", "turn the knob around", "give the dial a turn", "rotate the round knob"),
    },
    "disassemble-v3": {
        "train": ("take the nut off the peg", "lift the ring off the peg"),
        "heldout": ("remove the nut from the post", "pull the wrench ring up off the pole",
                    "unmount the nut from the peg", "get the ring off the peg"),
    },
    "door-close-v3": {
        "train": ("close the door", "shut the door"),
        "heldout": ("swing the door shut", "push the open door until it closes", "make the door close",
                    "the door is open, close it"),
    },
    "door-lock-v3": {
        "train": ("lock the door", "turn the lock on the door"),
        "heldout": ("rotate the latch to lock it", "secure the door with its lock", "twist the door lock closed",
                    "make the door locked"),
    },
    "door-unlock-v3": {
        "train": ("unlock the door", "turn the door lock open"),
        "heldout": ("rotate the latch to unlock it", "release the door lock", "twist the lock so the door opens",
                    "make the door unlocked"),
    },
    "drawer-close-v3": {
        "train": ("close the drawer", "shut the drawer"),
        "heldout": ("slide the drawer back in", "push the open drawer shut", "put the drawer away",
                    "the drawer is out, close it"),
    },
    "faucet-close-v3": {
        "train": ("turn off the faucet", "close the tap"),
        "heldout": ("shut off the water", "rotate the tap handle to stop the water", "turn the faucet off",
                    "stop the faucet"),
    },
    "faucet-open-v3": {
        "train": ("turn on the faucet", "open the tap"),
        "heldout": ("let the water run", "rotate the tap handle to start the water", "turn the faucet on",
                    "start the faucet"),
    },
    "hammer-v3": {
        "train": ("use the hammer to hit the nail into the wall", "hammer the nail in"),
        "heldout": ("grab the hammer and pound the nail", "knock the nail into the board with the hammer",
                    "drive the peg in with the hammer", "take the hammer and bang the nail in"),
    },
    "hand-insert-v3": {
        "train": ("put the block in the hole", "insert the block into the hole"),
        "heldout": ("drop the cube into the opening", "place the block down into the slot",
                    "fit the block into the hole in the table", "sink the block into the hole"),
    },
    "handle-press-side-v3": {
        "train": ("push the handle down from the side", "press down on the side handle"),
        "heldout": ("push the lever down sideways", "lower the handle from the side", "press the side lever down",
                    "bring the handle down from its side"),
    },
    "handle-press-v3": {
        "train": ("push the handle down", "press down on the handle"),
        "heldout": ("push the lever down", "lower the handle", "press the lever all the way down",
                    "bring the handle down"),
    },
    "handle-pull-side-v3": {
        "train": ("lift the handle up from the side", "pull up on the side handle"),
        "heldout": ("raise the lever sideways", "pull the side lever upward", "lift the handle from its side",
                    "bring the handle up from the side"),
    },
    "handle-pull-v3": {
        "train": ("lift the handle up", "pull up on the handle"),
        "heldout": ("raise the lever", "pull the handle bar upward", "lift up the handle", "bring the handle up"),
    },
    "lever-pull-v3": {
        "train": ("lift the lever", "pull the lever upward"),
        "heldout": ("raise the lever arm", "flip the lever up", "pull the lever all the way up",
                    "move the lever to the top"),
    },
    "peg-insert-side-v3": {
        "train": ("insert the peg into the hole from the side", "push the peg sideways into the hole"),
        "heldout": ("grab the peg and slide it into the side opening", "plug the peg into the hole horizontally",
                    "fit the stick into the hole on the side", "put the peg into the slot from the side"),
    },
    "peg-unplug-side-v3": {
        "train": ("unplug the peg sideways", "pull the peg out of the hole"),
        "heldout": ("remove the plug from the side socket", "slide the peg out of its slot",
                    "take the peg out sideways", "pull the plug out horizontally"),
    },
    "pick-out-of-hole-v3": {
        "train": ("lift the peg out of the hole", "take the peg out of the hole"),
        "heldout": ("pull the stick up out of the opening", "remove the peg from the hole",
                    "get the peg out of the slot", "raise the peg out of its hole"),
    },
    "pick-place-wall-v3": {
        "train": ("pick up the puck and place it at the goal behind the wall", "lift the puck over the wall to the goal"),
        "heldout": ("carry the disc over the barrier and set it on the target", "raise the puck above the wall and drop it at the goal",
                    "take the puck past the wall to the marker", "move the puck over the wall onto the target"),
    },
    "plate-slide-back-side-v3": {
        "train": ("slide the plate sideways out of the cabinet", "pull the plate out to the side"),
        "heldout": ("get the dish out of the cabinet sideways", "drag the plate out from the side",
                    "move the plate sideways out of the shelf", "take the plate out to the side"),
    },
    "plate-slide-back-v3": {
        "train": ("slide the plate out of the cabinet", "pull the plate back out"),
        "heldout": ("get the dish out of the cabinet", "drag the plate back towards you",
                    "remove the plate from the shelf", "take the plate back out of the cabinet"),
    },
    "plate-slide-side-v3": {
        "train": ("slide the plate into the cabinet from the side", "push the plate sideways into the cabinet"),
        "heldout": ("put the dish into the cabinet sideways", "shove the plate into the shelf from the side",
                    "move the plate sideways into the cupboard", "slide the dish in from the side"),
    },
    "plate-slide-v3": {
        "train": ("slide the plate into the cabinet", "push the plate forward into the cabinet"),
        "heldout": ("put the dish into the cabinet", "shove the plate into the shelf",
                    "move the plate into the cupboard", "slide the dish forward into place"),
    },
    "push-back-v3": {
        "train": ("pull the puck back to the goal", "bring the puck back towards the robot"),
        "heldout": ("drag the disc towards yourself onto the target", "slide the puck back to the marker",
                    "move the puck closer to the robot, onto the goal", "draw the puck back to the goal spot"),
    },
    "push-wall-v3": {
        "train": ("push the puck past the wall to the goal", "slide the puck around the wall to the target"),
        "heldout": ("nudge the disc around the barrier to the marker", "shove the puck past the wall onto the goal",
                    "move the puck around the obstacle to the target", "push the puck to the goal going around the wall"),
    },
    "reach-wall-v3": {
        "train": ("move the hand over the wall to the goal", "reach past the wall to the target"),
        "heldout": ("get the gripper to the target on the other side of the wall", "go over the barrier to the marked point",
                    "put your hand at the goal behind the wall", "reach the marker beyond the wall"),
    },
    "shelf-place-v3": {
        "train": ("put the puck on the shelf", "place the puck onto the shelf"),
        "heldout": ("lift the disc and set it on the shelf", "store the puck up on the shelf",
                    "pick the puck up and leave it on the shelf", "move the puck onto the shelf"),
    },
    "soccer-v3": {
        "train": ("kick the ball into the goal", "push the soccer ball into the net"),
        "heldout": ("score a goal with the ball", "roll the ball into the soccer net",
                    "get the ball into the goal", "shove the football into the goal"),
    },
    "stick-pull-v3": {
        "train": ("use the stick to pull the thermos to the goal", "grab the stick and drag the thermos to the goal"),
        "heldout": ("with the stick, pull the bottle over to the target", "hook the flask with the stick and bring it to the goal",
                    "pick up the stick and drag the thermos to the marker", "use the rod to pull the thermos to the target"),
    },
    "stick-push-v3": {
        "train": ("use the stick to push the thermos to the goal", "grab the stick and shove the thermos to the goal"),
        "heldout": ("with the stick, push the bottle over to the target", "poke the flask to the goal using the stick",
                    "pick up the stick and shove the thermos to the marker", "use the rod to push the thermos to the target"),
    },
    "sweep-into-v3": {
        "train": ("brush the puck into the hole", "move the puck into the hole with a sweep"),
        "heldout": ("push the disc into the opening", "sweep the puck so it falls into the hole",
                    "get the puck into the hole in the table", "slide the puck into the hole"),
    },
    "sweep-v3": {
        "train": ("sweep the puck off the table", "brush the puck off the edge"),
        "heldout": ("push the disc off the side of the table", "sweep the puck over the edge",
                    "get the puck off the table", "knock the puck off the edge of the table"),
    },
    "window-close-v3": {
        "train": ("close the window", "shut the window by sliding it"),
        "heldout": ("slide the window shut", "push the window closed", "the window is open, close it",
                    "move the window pane until it is closed"),
    },
    "window-open-v3": {
        "train": ("open the window", "slide the window to open it"),
        "heldout": ("slide the glass pane open", "push the window open", "the window is shut, open it",
                    "move the window pane until it is open"),
    },
}
"""Paraphrases of every task's instruction: ``train`` (randomisation) and ``heldout`` (the
semantic suite) variants."""


def task_instruction_variants(task: str, perturbations) -> tuple[list[str], dict[str, range]]:
    """A task's instruction variants under ``perturbations`` (a
    :class:`~stepnft.envs.perturbations.Perturbations`) and each semantic segment's indices."""
    from stepnft.envs.perturbations import instruction_variants

    paraphrases = paraphrases_for(task) if perturbations.semantic else {}
    return instruction_variants(instruction_for(task), paraphrases, perturbations.semantic, perturbations.heldout)


def paraphrases_for(task: str) -> dict[str, tuple[str, ...]]:
    """The ``train`` and ``heldout`` paraphrases of a MetaWorld v3 task's instruction."""
    if task not in PARAPHRASES:
        raise unknown_task_error(task, sorted(PARAPHRASES))
    return PARAPHRASES[task]


def unknown_task_error(task: str, valid: list[str]) -> ValueError:
    """The one-line error for a task name MetaWorld does not have."""
    return ValueError(f"unknown MetaWorld task {task!r}; valid names: {', '.join(valid)}")


def instruction_for(task: str) -> str:
    """The instruction for a MetaWorld v3 task name, e.g. 'pick-place-v3'."""
    if task not in INSTRUCTIONS:
        raise unknown_task_error(task, sorted(INSTRUCTIONS))
    return INSTRUCTIONS[task]
