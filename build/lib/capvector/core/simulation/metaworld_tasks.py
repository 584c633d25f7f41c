"""The 50 Meta-World v3 tasks: names, instructions in words, difficulty groups, name validation.

The names are ours (the keys of INSTRUCTIONS), so validating a config does not import metaworld (0.4 s);
the first environment or expert built checks them against metaworld's v3 registry
(`check_against_metaworld`), so a metaworld upgrade that adds or renames a task fails loudly there
instead of silently drifting.
"""

from __future__ import annotations

import difflib
import functools

INSTRUCTIONS: dict[str, str] = {
    "assembly-v3": "pick up the nut and place it onto the peg",
    "basketball-v3": "pick up the ball and dunk it into the basket",
    "bin-picking-v3": "pick up the puck from one bin and place it into the other bin",
    "box-close-v3": "pick up the lid and close the box with it",
    "button-press-topdown-v3": "press the button down from the top",
    "button-press-topdown-wall-v3": "press the button down from the top behind the wall",
    "button-press-v3": "press the button from the front",
    "button-press-wall-v3": "press the button from the front behind the wall",
    "coffee-button-v3": "push the button on the coffee machine",
    "coffee-pull-v3": "pull the mug away from the coffee machine",
    "coffee-push-v3": "push the mug under the coffee machine",
    "dial-turn-v3": "rotate the dial",
    "disassemble-v3": "pick the nut off the peg",
    "door-close-v3": "close the door",
    "door-lock-v3": "lock the door by turning the lock",
    "door-open-v3": "open the door",
    "door-unlock-v3": "unlock the door by turning the lock",
    "drawer-close-v3": "push the drawer closed",
    "drawer-open-v3": "pull the drawer open",
    "faucet-close-v3": "rotate the faucet handle to close it",
    "faucet-open-v3": "rotate the faucet handle to open it",
    "hammer-v3": "pick up the hammer and hammer the nail into the wall",
    "hand-insert-v3": "insert the gripper into the hole",
    "handle-press-side-v3": "press the handle down from the side",
    "handle-press-v3": "press the handle down",
    "handle-pull-side-v3": "pull the handle up from the side",
    "handle-pull-v3": "pull the handle up",
    "lever-pull-v3": "pull the lever up",
    "peg-insert-side-v3": "pick up the peg and insert it into the hole from the side",
    "peg-unplug-side-v3": "pull the peg out of the hole from the side",
    "pick-out-of-hole-v3": "pick the puck up out of the hole",
    "pick-place-v3": "pick up the puck and place it at the goal",
    "pick-place-wall-v3": "pick up the puck and place it at the goal behind the wall",
    "plate-slide-back-side-v3": "slide the plate sideways back out of the cabinet",
    "plate-slide-back-v3": "slide the plate back out of the cabinet",
    "plate-slide-side-v3": "slide the plate sideways into the cabinet",
    "plate-slide-v3": "slide the plate into the cabinet",
    "push-back-v3": "push the puck backwards to the goal",
    "push-v3": "push the puck to the goal",
    "push-wall-v3": "push the puck around the wall to the goal",
    "reach-v3": "reach the goal position with the gripper",
    "reach-wall-v3": "reach the goal position behind the wall",
    "shelf-place-v3": "pick up the puck and place it on the shelf",
    "soccer-v3": "kick the ball into the goal",
    "stick-pull-v3": "grasp the stick and pull the box with it",
    "stick-push-v3": "grasp the stick and push the box with it",
    "sweep-into-v3": "sweep the puck into the hole",
    "sweep-v3": "sweep the puck off the table",
    "window-close-v3": "slide the window closed",
    "window-open-v3": "slide the window open",
}

# Difficulty groups as used by Seo et al. (2022) and Masked World Models (Seo et al., 2023), after
# Meta-World's own expert success statistics: easy 28, medium 11, hard 6, very hard 5.
DIFFICULTY_GROUPS: dict[str, tuple[str, ...]] = {
    "easy": tuple(
        f"{name}-v3"
        for name in (
            "button-press",
            "button-press-topdown",
            "button-press-topdown-wall",
            "button-press-wall",
            "coffee-button",
            "dial-turn",
            "door-close",
            "door-lock",
            "door-open",
            "door-unlock",
            "drawer-close",
            "drawer-open",
            "faucet-close",
            "faucet-open",
            "handle-press",
            "handle-press-side",
            "handle-pull",
            "handle-pull-side",
            "lever-pull",
            "plate-slide",
            "plate-slide-back",
            "plate-slide-back-side",
            "plate-slide-side",
            "reach",
            "reach-wall",
            "window-close",
            "window-open",
            "peg-unplug-side",
        )
    ),
    "medium": tuple(
        f"{name}-v3"
        for name in (
            "basketball",
            "bin-picking",
            "box-close",
            "coffee-pull",
            "coffee-push",
            "hammer",
            "peg-insert-side",
            "push-wall",
            "soccer",
            "sweep",
            "sweep-into",
        )
    ),
    "hard": tuple(
        f"{name}-v3"
        for name in ("assembly", "hand-insert", "pick-out-of-hole", "pick-place", "push", "push-back")
    ),
    "very_hard": tuple(
        f"{name}-v3" for name in ("shelf-place", "disassemble", "stick-pull", "stick-push", "pick-place-wall")
    ),
}

MT10_TASKS: tuple[str, ...] = (
    "reach-v3",
    "push-v3",
    "pick-place-v3",
    "door-open-v3",
    "drawer-open-v3",
    "drawer-close-v3",
    "button-press-topdown-v3",
    "peg-insert-side-v3",
    "window-open-v3",
    "window-close-v3",
)


TASK_NAMES: tuple[str, ...] = tuple(sorted(INSTRUCTIONS))


@functools.cache
def check_against_metaworld() -> None:
    """Fail loudly if metaworld's v3 tasks and our tables disagree (called where metaworld is loaded)."""
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    names = set(ALL_V3_ENVIRONMENTS)
    grouped = [t for group in DIFFICULTY_GROUPS.values() for t in group]
    if set(INSTRUCTIONS) != names or sorted(grouped) != sorted(names) or not set(MT10_TASKS) <= names:
        raise RuntimeError(
            "capvector's Meta-World task tables do not match metaworld's v3 tasks: "
            f"missing instructions {sorted(names - set(INSTRUCTIONS))}, "
            f"not in metaworld {sorted(set(INSTRUCTIONS) - names)}, "
            f"ungrouped {sorted(names - set(grouped))}, unknown {sorted(set(grouped) - names)}"
        )


def validate_task_names(names: list[str] | tuple[str, ...]) -> list[str]:
    """Return `names` as a list, or raise ValueError naming every unknown task and close matches."""
    names = list(names)
    if not names:
        raise ValueError("the task list is empty; give at least one Meta-World v3 task name")
    unknown = [n for n in names if n not in INSTRUCTIONS]
    if unknown:
        hints = []
        for name in unknown:
            close = difflib.get_close_matches(name, TASK_NAMES, n=3, cutoff=0.6)
            hints.append(f"{name!r} (did you mean {', '.join(close)}?)" if close else repr(name))
        raise ValueError(
            f"unknown Meta-World v3 task name(s): {'; '.join(hints)}. "
            f"Valid names end in '-v3', e.g. {', '.join(TASK_NAMES[:3])}"
        )
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise ValueError(f"task list names a task more than once: {duplicates}")
    return names


def instruction(task: str) -> str:
    """The instruction in words for one task."""
    validate_task_names([task])
    return INSTRUCTIONS[task]


def difficulty(task: str) -> str:
    """The difficulty group ('easy', 'medium', 'hard', 'very_hard') of one task."""
    validate_task_names([task])
    return next(group for group, tasks in DIFFICULTY_GROUPS.items() if task in tasks)
