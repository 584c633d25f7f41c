"""Write a `DemoDataset` as a LeRobotDataset v3.0 folder (layout and names: lerobot_layout.py), so that
LeRobot and anything reading its format (pandas, datasets, DuckDB) can use capvector's demonstrations.

Every Parquet file is written with pyarrow; vectors as fixed-size lists, images as LeRobot's `image`
feature (PNG bytes: lossless, so the folder reads back to the same pixels). The folder is built beside
the target and renamed into place: an interrupted export leaves no half-written dataset.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from capvector.core.simulation.demos import DemoDataset
from capvector.core.simulation.envs import PROPRIO_DIM
from capvector.core.simulation.lerobot_layout import (
    ACTION_KEY,
    CAPVECTOR_PATH,
    CHUNKS_SIZE,
    CODEBASE_VERSION,
    DATA_FILES_SIZE_IN_MB,
    DATA_PATH,
    DONE_KEY,
    EPISODES_PATH,
    FIELD_KEYS,
    INFO_PATH,
    ROBOT_TYPE,
    STATE_KEY,
    STATS_PATH,
    TASKS_PATH,
    VIDEO_FILES_SIZE_IN_MB,
    LeRobotFormatError,
    chunk_file,
    extra_key,
    feature_names,
    frames_per_file,
    image_key,
    image_stats,
    numeric_stats,
)
from capvector.durable import fsync_files

CAPVECTOR_FORMAT = 1  # of meta/capvector.json


@dataclass(frozen=True)
class Feature:
    """One LeRobot feature: its key, where its values come from (a DemoDataset field or computed), and
    what info.json says of it."""

    key: str
    values: np.ndarray  # one row per frame
    dtype: str  # LeRobot's: a numpy dtype name, or "image"
    names: list[str] | None = None

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.values.shape[1:]) or (1,)

    def info(self) -> dict[str, Any]:
        names = ["height", "width", "channels"] if self.dtype == "image" else self.names
        return {"dtype": self.dtype, "shape": list(self.shape), "names": names}

    def bytes_per_frame(self) -> int:
        return int(np.prod(self.shape)) * self.values.dtype.itemsize


def episode_bounds(episode: np.ndarray, step: np.ndarray) -> list[tuple[int, int]]:
    """(first row, end row) of each episode; LeRobot wants episodes numbered 0..n-1 in row order, each
    one contiguous run of rows with frame_index 0..length-1."""
    starts = np.flatnonzero(np.diff(episode, prepend=episode[:1] - 1))
    ends = [*starts[1:].tolist(), len(episode)]
    bounds = list(zip(starts.tolist(), ends, strict=True))
    if episode[starts].tolist() != list(range(len(bounds))):
        raise LeRobotFormatError(
            "the dataset's episodes are not numbered 0..n-1 in row order, as LeRobot's episode_index must be"
        )
    for start, end in bounds:
        if step[start:end].tolist() != list(range(end - start)):
            raise LeRobotFormatError(f"episode {int(episode[start])}: its steps are not 0..{end - start - 1}")
    return bounds


def features_of(dataset: DemoDataset, fps: int, bounds: list[tuple[int, int]]) -> list[Feature]:
    """The dataset's features in info.json order: state, action, image, capvector.* extras, then
    LeRobot's per-frame indices and next.done (true on each episode's last frame, `bounds`)."""
    t = {key: tensor.numpy() for key, tensor in dataset.tensors.items()}
    features = [
        Feature(STATE_KEY, t["state"], str(t["state"].dtype), feature_names(STATE_KEY, t["state"].shape[1:])),
        Feature(
            ACTION_KEY, t["action"], str(t["action"].dtype), feature_names(ACTION_KEY, t["action"].shape[1:])
        ),
    ]
    if "image" in t:
        features.append(Feature(image_key(dataset.meta.camera), t["image"], "image"))
    proprio_is_state = "proprio" in t and np.array_equal(t["proprio"], t["state"][:, :PROPRIO_DIM])
    skip = {"state", "action", "image", *FIELD_KEYS} | ({"proprio"} if proprio_is_state else set())
    for field in sorted(set(t) - skip):
        key = extra_key(field)
        features.append(Feature(key, t[field], str(t[field].dtype), feature_names(key, t[field].shape[1:])))
    done = np.zeros(len(dataset), dtype=bool)
    done[[end - 1 for _, end in bounds]] = True
    return [
        *features,
        Feature("timestamp", (t["step"] / fps).astype(np.float32), "float32"),
        Feature("frame_index", t["step"], "int64"),
        Feature("episode_index", t["episode"], "int64"),
        Feature("index", np.arange(len(dataset), dtype=np.int64), "int64"),
        Feature("task_index", t["task"], "int64"),
        Feature(DONE_KEY, done, "bool"),
    ]


def _arrow(values: np.ndarray) -> pa.Array:
    """A numpy column as Arrow: one value per row, or nested fixed-size lists for a vector or matrix."""
    array = pa.array(np.ascontiguousarray(values).reshape(-1))
    for size in reversed(values.shape[1:]):
        array = pa.FixedSizeListArray.from_arrays(array, size)
    return array


def _png_column(images: np.ndarray, frame_index: np.ndarray) -> pa.Array:
    """LeRobot's (Hugging Face datasets') image column: a struct of PNG bytes and a file name."""
    from PIL import Image

    encoded = []
    for image in images:
        buffer = io.BytesIO()
        Image.fromarray(image).save(buffer, format="PNG")
        encoded.append(buffer.getvalue())
    paths = [f"frame-{int(i):06d}.png" for i in frame_index]
    return pa.StructArray.from_arrays(
        [pa.array(encoded, pa.binary()), pa.array(paths, pa.string())], names=["bytes", "path"]
    )


def _frames_table(features: list[Feature], rows: slice) -> pa.Table:
    frame_index = next(f.values for f in features if f.key == "frame_index")[rows]
    columns = {
        f.key: _png_column(f.values[rows], frame_index) if f.dtype == "image" else _arrow(f.values[rows])
        for f in features
    }
    return pa.table(columns)


def data_files(bounds: list[tuple[int, int]], bytes_per_frame: int, limit_mb: float) -> list[list[int]]:
    """Episodes grouped into data files in order, a file closed before an episode would take it past
    `limit_mb` (an episode is never split; a file holds at least one)."""
    budget = frames_per_file(bytes_per_frame, limit_mb)
    files: list[list[int]] = []
    frames = 0
    for episode, (start, end) in enumerate(bounds):
        if not files or frames + (end - start) > budget:
            files.append([])
            frames = 0
        files[-1].append(episode)
        frames += end - start
    return files


def _write_parquet(table: pa.Table, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path)


def _write_json(data: Any, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=4, ensure_ascii=False) + "\n")


def _tasks_table(instructions: list[str]) -> pa.Table:
    """meta/tasks.parquet as LeRobot writes it with pandas: the task text is the index, named "task"."""
    import pandas as pd

    frame = pd.DataFrame(
        {"task_index": np.arange(len(instructions), dtype=np.int64)},
        index=pd.Index(instructions, name="task"),
    )
    return pa.Table.from_pandas(frame)


def _episodes_table(
    bounds: list[tuple[int, int]], files: list[list[int]], task: np.ndarray, instructions: list[str]
) -> pa.Table:
    where = {episode: chunk_file(number) for number, group in enumerate(files) for episode in group}
    rows = []
    for episode, (start, end) in enumerate(bounds):
        tasks = [instructions[i] for i in dict.fromkeys(task[start:end].tolist())]
        chunk, file = where[episode]
        rows.append({
            "episode_index": episode, "tasks": tasks, "length": end - start,
            "data/chunk_index": chunk, "data/file_index": file,
            "dataset_from_index": start, "dataset_to_index": end,
            "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
        })  # fmt: skip
    types = {key: pa.int64() for key in rows[0]} | {"tasks": pa.list_(pa.string())}
    return pa.table({key: pa.array([r[key] for r in rows], types[key]) for key in rows[0]})


def _info(features: list[Feature], n_episodes: int, n_tasks: int, fps: int) -> dict[str, Any]:
    n_frames = len(features[0].values)
    return {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": ROBOT_TYPE,
        "total_episodes": n_episodes,
        "total_frames": n_frames,
        "total_tasks": n_tasks,
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILES_SIZE_IN_MB,
        "video_files_size_in_mb": VIDEO_FILES_SIZE_IN_MB,
        "fps": fps,
        "splits": {"train": f"0:{n_episodes}"},
        "data_path": DATA_PATH,
        "video_path": None,  # images are stored in the data files, not as videos
        "features": {f.key: f.info() for f in features},
    }


def _stats(features: list[Feature]) -> dict[str, dict[str, list]]:
    return {f.key: image_stats(f.values) if f.dtype == "image" else numeric_stats(f.values) for f in features}


def _check_tasks(dataset: DemoDataset) -> list[str]:
    instructions = list(dataset.meta.instructions)
    if len(set(instructions)) != len(instructions):
        raise LeRobotFormatError(
            f"tasks.parquet needs one text per task; the instructions repeat: {instructions}"
        )
    used = dataset.tensors["task"]
    if len(used) and (int(used.min()) < 0 or int(used.max()) >= len(instructions)):
        raise LeRobotFormatError(
            f"the dataset's task indices are not within its {len(instructions)} instructions"
        )
    return instructions


def write_folder(
    dataset: DemoDataset,
    root: Path,
    fps: int,
    source_artifact: str | None,
    limit_mb: float = DATA_FILES_SIZE_IN_MB,
) -> dict[str, Any]:
    """Write every file of the v3.0 layout under `root` (an empty folder); what was written, in numbers."""
    instructions = _check_tasks(dataset)
    t = dataset.tensors
    bounds = episode_bounds(t["episode"].numpy(), t["step"].numpy())
    features = features_of(dataset, fps, bounds)
    files = data_files(bounds, sum(f.bytes_per_frame() for f in features), limit_mb)
    for number, group in enumerate(files):
        chunk, file = chunk_file(number)
        rows = slice(bounds[group[0]][0], bounds[group[-1]][1])
        _write_parquet(
            _frames_table(features, rows), root / DATA_PATH.format(chunk_index=chunk, file_index=file)
        )
    episodes = root / EPISODES_PATH.format(chunk_index=0, file_index=0)
    _write_parquet(_episodes_table(bounds, files, t["task"].numpy(), instructions), episodes)
    _write_parquet(_tasks_table(instructions), root / TASKS_PATH)
    info = _info(features, len(bounds), len(instructions), fps)
    _write_json(info, root / INFO_PATH)
    _write_json(_stats(features), root / STATS_PATH)
    capvector = {"format": CAPVECTOR_FORMAT, "source_artifact": source_artifact}
    _write_json({**capvector, "dataset": dataset.meta.model_dump(mode="json")}, root / CAPVECTOR_PATH)
    return {key: info[key] for key in ("total_episodes", "total_frames", "total_tasks", "fps")} | {
        "data_files": len(files),
        "features": [f.key for f in features],
    }


def write_lerobot(
    dataset: DemoDataset,
    directory: str | os.PathLike,
    fps: int,
    source_artifact: str | None = None,
    limit_mb: float = DATA_FILES_SIZE_IN_MB,
) -> dict[str, Any]:
    """Write `dataset` as a LeRobotDataset v3.0 folder at `directory` (a new path or an empty folder),
    built beside it and renamed into place. `source_artifact` (its artifact id) goes to
    meta/capvector.json, for the lineage of a later import. Returns totals, files and features written."""
    target = Path(directory)
    if target.exists() and (not target.is_dir() or any(target.iterdir())):
        raise FileExistsError(
            f"{target} exists and is not an empty folder: export writes a new dataset folder"
        )
    target.parent.mkdir(parents=True, exist_ok=True)
    staged = target.parent / f".{target.name}.lerobot-{uuid.uuid4().hex[:8]}"
    staged.mkdir()
    try:
        summary = write_folder(dataset, staged, fps, source_artifact, limit_mb)
        for folder in sorted((p for p in staged.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts)):
            fsync_files(folder)  # the deepest first, each folder after its files
        fsync_files(staged)
        if target.exists():
            target.rmdir()  # empty, checked above
        os.rename(staged, target)
    finally:
        shutil.rmtree(staged, ignore_errors=True)
    return {"path": str(target), **summary}
