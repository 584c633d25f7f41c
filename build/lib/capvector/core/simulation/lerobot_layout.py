"""LeRobotDataset v3.0 as capvector writes and reads it: file names, feature names and statistics.

A v3.0 folder (as LeRobot's src/lerobot/datasets/utils.py lays it out) holds `meta/info.json` (codebase
version, fps, features with dtype/shape/names, path templates, totals), `meta/stats.json`,
`meta/tasks.parquet` (task text as the pandas index "task", column task_index),
`meta/episodes/chunk-XXX/file-YYY.parquet` (one row per episode: where its frames lie) and
`data/chunk-XXX/file-YYY.parquet` (one row per frame). capvector adds `meta/capvector.json` (the
`DatasetMeta` it exported), which LeRobot ignores and which makes an export read back exactly.

How `DemoDataset` fields map to features (`FIELD_KEYS`, `extra_key`): state -> observation.state,
action -> action, image -> observation.images.<camera>, episode/step/task -> episode_index/frame_index/
task_index; every other field (privileged, patch_xyz, proprio where it is not state[:4]) -> capvector.<field>,
outside `observation.` so that a LeRobot policy does not take training-only features as inputs.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

CODEBASE_VERSION = "v3.0"
METAWORLD_FPS = 80  # Meta-World steps MuJoCo 5 frames of 2.5 ms per action: 12.5 ms, 80 Hz (LeRobot's too)
ROBOT_TYPE = "sawyer"  # Meta-World's arm
CHUNKS_SIZE = 1000  # files per chunk folder
DATA_FILES_SIZE_IN_MB = 100  # a data file is closed once the next episode would take it past this
VIDEO_FILES_SIZE_IN_MB = 200

INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
TASKS_PATH = "meta/tasks.parquet"
CAPVECTOR_PATH = "meta/capvector.json"
EPISODES_DIR = "meta/episodes"
CHUNK_FILE_PATTERN = "chunk-{chunk_index:03d}/file-{file_index:03d}"
EPISODES_PATH = EPISODES_DIR + "/" + CHUNK_FILE_PATTERN + ".parquet"
DATA_PATH = "data/" + CHUNK_FILE_PATTERN + ".parquet"
VIDEO_PATH = "videos/{video_key}/" + CHUNK_FILE_PATTERN + ".mp4"

STATE_KEY = "observation.state"
ACTION_KEY = "action"
IMAGE_PREFIX = "observation.images."
EXTRA_PREFIX = "capvector."
# DemoDataset field -> LeRobot feature, for the fields with a LeRobot name of their own
FIELD_KEYS = {
    "state": STATE_KEY,
    "action": ACTION_KEY,
    "episode": "episode_index",
    "step": "frame_index",
    "task": "task_index",
}
# LeRobot's DEFAULT_FEATURES: every frame has them
INDEX_KEYS = ("timestamp", "frame_index", "episode_index", "index", "task_index")
DONE_KEY = "next.done"
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)  # LeRobot's q01 … q99, for quantile normalization

ACTION_NAMES = ["delta_x", "delta_y", "delta_z", "gripper"]
_AXES = ("x", "y", "z", "quat_0", "quat_1", "quat_2", "quat_3")  # quaternion order differs between tasks
_OBJECT = [f"{part}_{axis}" for part in ("obj1", "obj2") for axis in _AXES]
_FRAME = ["hand_x", "hand_y", "hand_z", "gripper_distance", *_OBJECT]
STATE_NAMES = [*_FRAME, *(f"prev_{n}" for n in _FRAME), "goal_x", "goal_y", "goal_z"]  # Meta-World's 39
PRIVILEGED_NAMES = [f"{part}_{axis}" for part in ("object", "goal", "tcp") for axis in ("x", "y", "z")]


class LeRobotFormatError(ValueError):
    """A folder that is not a LeRobotDataset v3.0 capvector can read; the message names file and field."""


def extra_key(field: str) -> str:
    return EXTRA_PREFIX + field


def image_key(camera: str) -> str:
    return IMAGE_PREFIX + (camera or "camera")


def feature_names(key: str, shape: tuple[int, ...]) -> list[str] | None:
    """Per-dimension names of a 1-D feature where capvector knows them (info.json `names`)."""
    known = {STATE_KEY: STATE_NAMES, ACTION_KEY: ACTION_NAMES, extra_key("privileged"): PRIVILEGED_NAMES}
    names = known.get(key)
    return names if names is not None and shape == (len(names),) else None


def numeric_stats(values: np.ndarray) -> dict[str, list]:
    """min/max/mean/std/count and q01…q99 over frames (axis 0), NaN ignored, as LeRobot keeps them: each
    a list shaped like one frame's value (a scalar feature: a list of one), count a list of one."""
    array = np.asarray(values, dtype=np.float64)
    if array.ndim == 1:
        array = array[:, None]
    with warnings.catch_warnings():  # a dimension NaN in every frame (a patch seeing nothing) stays NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        stats = {
            "min": np.nanmin(array, axis=0),
            "max": np.nanmax(array, axis=0),
            "mean": np.nanmean(array, axis=0),
            "std": np.nanstd(array, axis=0),
        }
        for q in QUANTILES:
            stats[f"q{round(q * 100):02d}"] = np.nanquantile(array, q, axis=0)
    return {**{k: v.tolist() for k, v in stats.items()}, "count": [int(array.shape[0])]}


def image_stats(images: np.ndarray, block: int = 4096) -> dict[str, list]:
    """Per-channel min/max/mean/std of uint8 (N, H, W, C) images scaled to [0, 1], shaped (C, 1, 1) as
    LeRobot keeps image stats; count is the number of frames. Summed in blocks of frames: no float copy
    of the whole array."""
    channels = images.shape[-1]
    total, squares = np.zeros(channels), np.zeros(channels)
    low, high = np.full(channels, 255.0), np.zeros(channels)
    for start in range(0, len(images), block):
        part = images[start : start + block].reshape(-1, channels).astype(np.float64)
        total += part.sum(axis=0)
        squares += (part**2).sum(axis=0)
        low, high = np.minimum(low, part.min(axis=0)), np.maximum(high, part.max(axis=0))
    pixels = images.size // channels
    mean = total / pixels
    std = np.sqrt(np.maximum(squares / pixels - mean**2, 0.0))

    def shaped(v: np.ndarray) -> list:
        return (v / 255.0).reshape(channels, 1, 1).tolist()

    stats = {"min": shaped(low), "max": shaped(high), "mean": shaped(mean), "std": shaped(std)}
    return {**stats, "count": [int(len(images))]}


def frames_per_file(bytes_per_frame: int, limit_mb: float = DATA_FILES_SIZE_IN_MB) -> int:
    """How many frames one data file takes before it reaches `limit_mb` (at least one)."""
    return max(1, math.floor(limit_mb * 1024 * 1024 / max(1, bytes_per_frame)))


def chunk_file(number: int) -> tuple[int, int]:
    """(chunk_index, file_index) of the `number`-th file: CHUNKS_SIZE files per chunk folder."""
    return divmod(number, CHUNKS_SIZE)
