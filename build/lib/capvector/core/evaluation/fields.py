"""What each user-set `EvalConfig` field means and defaults to, declared once: the model's fields
(capvector.core.evaluation.rollouts) and `capvector evaluate`'s options (capvector.flows.cli.eval_options)
both read this table. Constraints stay on the model, which names the field a bad value fails. No imports, so
the command line builds its options without loading MuJoCo, torch or pydantic."""

from typing import Any, NamedTuple


class EvalField(NamedTuple):
    flag: str
    kind: type
    default: Any
    help: str


EVAL_FIELDS = {
    "episodes_per_task": EvalField("--episodes", int, 20, "episodes (goal variations) per task"),
    "horizon": EvalField("--horizon", int, 500, "steps per episode at most (Meta-World's limit: 500)"),
    "execute_steps": EvalField("--execute-steps", int, 1, "actions executed per predicted chunk"),
    "obs_mode": EvalField("--obs-mode", str, "state", "state | pixels: what the policy observes"),
    "camera": EvalField("--camera", str, "corner2", "pixels: camera (another tests generalization)"),
    "image_size": EvalField("--image-size", int, 64, "pixels: image side"),
    "record_video": EvalField("--video", int, 0, "episodes per task recorded as mp4 video artifacts"),
    "video_size": EvalField("--video-size", int, 256, "video frames' side (apart from the policy's images)"),
    "batch_size": EvalField("--batch-size", int, 64, "envs stepped together (memory; results equal)"),
}
