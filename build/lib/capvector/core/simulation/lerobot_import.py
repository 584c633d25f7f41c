"""Read a LeRobotDataset v3.0 folder into a `DemoDataset` (layout and names: lerobot_layout.py).

What is read: observation.state and action (required), one `image` feature (capvector's demos hold one
camera), every capvector.<field> feature, and the per-frame indices. Episodes are checked against
meta/episodes (contiguous rows, frame_index 0..length-1, the index column). A folder that capvector
exported reads back exactly, meta included (meta/capvector.json, used when the data still hash to
it); any other folder gets a `DatasetMeta` made from what it says (tasks by their text, or their
Meta-World name where the text is capvector's instruction for one). Video features cannot be decoded
here and are left out with a note. Every refusal is a LeRobotFormatError naming the file and field.
"""

from __future__ import annotations

import io
import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import torch
from pydantic import ValidationError

from capvector.core.simulation.demos import DatasetMeta, DemoDataset
from capvector.core.simulation.envs import PROPRIO_DIM
from capvector.core.simulation.lerobot_layout import (
    ACTION_KEY,
    CAPVECTOR_PATH,
    CODEBASE_VERSION,
    DONE_KEY,
    EPISODES_DIR,
    EXTRA_PREFIX,
    IMAGE_PREFIX,
    INDEX_KEYS,
    INFO_PATH,
    STATE_KEY,
    TASKS_PATH,
    LeRobotFormatError,
)
from capvector.core.simulation.metaworld_tasks import INSTRUCTIONS

EPISODE_COLUMNS = ("episode_index", "length", "dataset_from_index", "dataset_to_index", "data/chunk_index",
                   "data/file_index")  # fmt: skip


@dataclass
class LeRobotImport:
    """A folder read back: the dataset, the folder's fps, notes on what was left out, and the artifact
    capvector exported it from (named by meta/capvector.json, only when the data still match it)."""

    dataset: DemoDataset
    fps: float
    notes: list[str] = field(default_factory=list)
    source_artifact: str | None = None


def _json(root: Path, rel: str) -> Any:
    path = root / rel
    if not path.is_file():
        raise LeRobotFormatError(f"{root} is not a LeRobotDataset: {rel} is missing")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise LeRobotFormatError(f"{path} is not valid JSON: {err}") from err


def load_info(root: Path) -> dict[str, Any]:
    """meta/info.json, checked: codebase v3.0, fps, data_path, and features holding state and action."""
    info = _json(root, INFO_PATH)
    if not isinstance(info, dict):
        raise LeRobotFormatError(f"{root / INFO_PATH} is not a JSON object")
    version = info.get("codebase_version")
    if version != CODEBASE_VERSION:
        raise LeRobotFormatError(
            f"{root / INFO_PATH}: codebase_version is {version!r}, not {CODEBASE_VERSION!r}; capvector reads "
            "LeRobotDataset v3.0 only (LeRobot converts v2.1 with lerobot.scripts.convert_dataset_v21_to_v30)"
        )
    for key, kind in (("fps", (int, float)), ("data_path", str), ("features", dict)):
        if not isinstance(info.get(key), kind):
            raise LeRobotFormatError(f"{root / INFO_PATH}: field {key!r} is missing or not a {kind}")
    for key in (STATE_KEY, ACTION_KEY, *INDEX_KEYS):
        feature = info["features"].get(key)
        if not isinstance(feature, dict) or not isinstance(feature.get("shape"), list):
            raise LeRobotFormatError(
                f"{root / INFO_PATH}: features has no {key!r} (with a dtype and shape); capvector needs "
                f"{STATE_KEY}, {ACTION_KEY} and LeRobot's per-frame indices"
            )
    return info


def _read(path: Path, columns: list[str], what: str) -> pa.Table:
    if not path.is_file():
        raise LeRobotFormatError(f"{path} is missing ({what})")
    names = pq.read_schema(path).names
    missing = [c for c in columns if c not in names]
    if missing:
        raise LeRobotFormatError(f"{path} has no column(s) {missing} ({what}); it has {names}")
    return pq.read_table(path, columns=columns)


def load_tasks(root: Path) -> dict[int, str]:
    """task_index -> task text from meta/tasks.parquet (the text is the pandas index, named "task")."""
    path = root / TASKS_PATH
    if not path.is_file():
        raise LeRobotFormatError(f"{root} is not a LeRobotDataset: {TASKS_PATH} is missing")
    schema = pq.read_schema(path)
    pandas_meta = json.loads((schema.metadata or {}).get(b"pandas", b"{}"))
    text = next((c for c in ["task", *pandas_meta.get("index_columns", [])] if c in schema.names), None)
    if text is None or not isinstance(text, str):
        raise LeRobotFormatError(
            f"{path} has no task text column ('task' or the pandas index); it has {schema.names}"
        )
    table = _read(path, ["task_index", text], "the tasks")
    indices, texts = table["task_index"].to_pylist(), table[text].to_pylist()
    if len(set(indices)) != len(indices):
        raise LeRobotFormatError(f"{path}: task_index repeats")
    return dict(zip(indices, texts, strict=True))


def load_episodes(root: Path) -> dict[str, np.ndarray]:
    """The episode rows of every meta/episodes/chunk-*/file-*.parquet, by episode_index (0..n-1)."""
    paths = sorted((root / EPISODES_DIR).glob("chunk-*/file-*.parquet"))
    if not paths:
        raise LeRobotFormatError(
            f"{root} is not a LeRobotDataset: {EPISODES_DIR} holds no chunk-*/file-*.parquet"
        )
    table = pa.concat_tables([_read(p, list(EPISODE_COLUMNS), "the episodes") for p in paths])
    order = np.argsort(table["episode_index"].to_numpy(), kind="stable")
    episodes = {c: table[c].to_numpy()[order].astype(np.int64) for c in EPISODE_COLUMNS}
    if episodes["episode_index"].tolist() != list(range(len(order))):
        raise LeRobotFormatError(f"{root / EPISODES_DIR}: episode_index is not 0..{len(order) - 1}")
    return episodes


def _is_list(array: pa.Array) -> bool:
    kind = array.type
    return pa.types.is_list(kind) or pa.types.is_fixed_size_list(kind) or pa.types.is_large_list(kind)


def _numpy(column: pa.ChunkedArray, shape: list[int], where: str) -> np.ndarray:
    """A column of (nested, fixed-size or not) lists as one (N, *shape) array; a column of scalars
    (shape [1]: LeRobot's indices, a scalar field) as (N,)."""
    array = column.combine_chunks()
    rows = len(array)
    scalar = shape == [1] and not _is_list(array)
    while _is_list(array):
        array = pc.list_flatten(array)
    values = array.to_numpy(zero_copy_only=False)
    shape = [] if scalar else shape
    if values.size != rows * int(np.prod(shape or [1])):
        raise LeRobotFormatError(f"{where}: {values.size} values for {rows} frames of shape {shape}")
    return values.reshape(rows, *shape)


def _images(column: pa.ChunkedArray, where: str) -> np.ndarray | None:
    """uint8 (N, H, W, 3) from an image column's encoded bytes; None when it holds no bytes."""
    from PIL import Image

    encoded = column.combine_chunks().field("bytes").to_pylist()
    if any(b is None for b in encoded):
        return None
    try:
        return np.stack([np.asarray(Image.open(io.BytesIO(b)).convert("RGB")) for b in encoded])
    except OSError as err:
        raise LeRobotFormatError(f"{where}: an image does not decode: {err}") from err


def choose_columns(info: dict[str, Any], notes: list[str]) -> tuple[list[str], str | None]:
    """The data columns to read (state, action, capvector extras, indices) and the one image feature."""
    features = info["features"]
    images = [k for k, f in features.items() if f.get("dtype") == "image"]
    videos = [k for k, f in features.items() if f.get("dtype") == "video"]
    extras = sorted(k for k in features if k.startswith(EXTRA_PREFIX))
    image = images[0] if len(images) == 1 and len(features[images[0]]["shape"]) == 3 else None
    if videos:
        notes.append(f"video features left out (capvector does not decode videos): {videos}")
    if images and image is None:
        notes.append(f"image features left out (capvector's demos hold one camera): {images}")
    known = {STATE_KEY, ACTION_KEY, DONE_KEY, *INDEX_KEYS, *extras, *images, *videos}
    ignored = sorted(set(features) - known)
    if ignored:
        notes.append(f"features not read (no capvector field): {ignored}")
    return [STATE_KEY, ACTION_KEY, *extras, *INDEX_KEYS], image


def load_frames(
    root: Path, info: dict[str, Any], episodes: dict[str, np.ndarray], columns: list[str]
) -> pa.Table:
    """The data files the episodes point at, in order of their `index` column."""
    pairs = dict.fromkeys(
        zip(episodes["data/chunk_index"].tolist(), episodes["data/file_index"].tolist(), strict=True)
    )
    tables = []
    for chunk, file in pairs:
        try:
            rel = info["data_path"].format(chunk_index=chunk, file_index=file)
        except (KeyError, IndexError, ValueError) as err:
            raise LeRobotFormatError(
                f"{root / INFO_PATH}: data_path {info['data_path']!r} does not format: {err}"
            ) from err
        tables.append(_read(root / rel, columns, f"frames of episodes in chunk {chunk} file {file}"))
    table = pa.concat_tables(tables)
    return table.take(pc.sort_indices(table["index"]))


def check_frames(
    root: Path, info: dict[str, Any], episodes: dict[str, np.ndarray], frames: dict[str, np.ndarray]
):
    """Rows 0..N-1 in `index` order; each episode's rows where meta/episodes says, frame_index 0..len-1."""
    n = len(frames["index"])
    for key, count in (("total_frames", n), ("total_episodes", len(episodes["episode_index"]))):
        if info.get(key) is not None and info[key] != count:
            raise LeRobotFormatError(f"{root / INFO_PATH}: {key} is {info[key]}, the folder holds {count}")
    if frames["index"].tolist() != list(range(n)):
        raise LeRobotFormatError(f"{root / 'data'}: the index column is not 0..{n - 1}")
    spans = ("episode_index", "dataset_from_index", "dataset_to_index", "length")
    for e, start, end, length in zip(*(episodes[c].tolist() for c in spans), strict=True):
        rows = slice(int(start), int(end))
        if end - start != length or not 0 <= start < end <= n:
            raise LeRobotFormatError(
                f"{root / EPISODES_DIR}: episode {e} spans rows {start}..{end} of {n}, length {length}"
            )
        if (frames["episode_index"][rows] != e).any() or frames["frame_index"][rows].tolist() != list(
            range(length)
        ):
            raise LeRobotFormatError(
                f"{root / 'data'}: episode {e}'s rows {start}..{end} are not its frames 0..{length - 1}"
            )
    if int(episodes["length"].sum()) != n:
        raise LeRobotFormatError(
            f"{root / EPISODES_DIR}: the episodes' lengths add up to {episodes['length'].sum()}, not {n}"
        )


def _tensors(frames: dict[str, np.ndarray], tasks: dict[int, str], root: Path):
    """DemoDataset tensors, and the instruction of each task index (tasks.parquet's, in index order)."""
    ordered = sorted(tasks)
    unknown = sorted(set(frames["task_index"].tolist()) - set(ordered))
    if unknown:
        raise LeRobotFormatError(f"{root / TASKS_PATH} has no task for task_index {unknown} used in the data")
    position = {index: i for i, index in enumerate(ordered)}  # 0..T-1 already, unless tasks were removed
    tensors = {
        "state": torch.from_numpy(frames[STATE_KEY].astype(np.float32).reshape(len(frames["index"]), -1)),
        "action": torch.from_numpy(frames[ACTION_KEY].astype(np.float32).reshape(len(frames["index"]), -1)),
        "episode": torch.from_numpy(frames["episode_index"].astype(np.int64)),
        "step": torch.from_numpy(frames["frame_index"].astype(np.int64)),
        "task": torch.tensor([position[i] for i in frames["task_index"].tolist()], dtype=torch.int64),
    }
    for key in (k for k in frames if k.startswith(EXTRA_PREFIX)):
        tensors[key.removeprefix(EXTRA_PREFIX)] = torch.from_numpy(np.array(frames[key]))
    if "proprio" not in tensors:
        tensors["proprio"] = tensors["state"][:, :PROPRIO_DIM].clone()
    return tensors, [tasks[i] for i in ordered]


def synthesized_meta(instructions: list[str], tensors: dict[str, torch.Tensor], camera: str) -> DatasetMeta:
    """What a folder capvector did not write says of itself: tasks by their Meta-World name where the text
    is capvector's instruction for one (else by the text), no seeds, no collection settings."""
    names = {text: name for name, text in INSTRUCTIONS.items()}
    lengths = torch.bincount(tensors["episode"]).tolist()
    per_task = Counter(tensors["task"][tensors["step"] == 0].tolist())
    image = tensors.get("image")
    return DatasetMeta(
        tasks=[names.get(text, text) for text in instructions],
        instructions=instructions,
        obs_mode="pixels" if image is not None else "state",
        camera=camera,
        image_size=int(image.shape[1]) if image is not None else 0,
        horizon=max(lengths, default=0),
        episodes_per_task=max(per_task.values(), default=0),
        seed_offset=0,
        success_tail=0,
        goal_sampling="unknown",
        seeds={},
        failures={},
        n_episodes=len(lengths),
        n_steps=len(tensors["action"]),
    )


def exported_meta(
    root: Path, tensors: dict[str, torch.Tensor], notes: list[str]
) -> tuple[DemoDataset | None, str | None]:
    """The dataset as capvector exported it (meta/capvector.json), when the data still hash to it."""
    if not (root / CAPVECTOR_PATH).is_file():
        return None, None
    stored = _json(root, CAPVECTOR_PATH)
    try:
        meta = DatasetMeta.model_validate(stored.get("dataset") if isinstance(stored, dict) else None)
    except ValidationError as err:
        raise LeRobotFormatError(
            f"{root / CAPVECTOR_PATH}: 'dataset' is not capvector dataset metadata: {err}"
        ) from err
    try:
        dataset = DemoDataset(tensors, meta)
    except ValueError:
        dataset = None
    if dataset is None or dataset.compute_hash() != meta.content_hash:
        notes.append(
            f"{CAPVECTOR_PATH} describes other data (the folder changed after capvector wrote it): not used"
        )
        return None, None
    return dataset, stored.get("source_artifact")


def read_lerobot(directory: str | Path) -> LeRobotImport:
    """Read a LeRobotDataset v3.0 folder into a DemoDataset (see the module docstring)."""
    root = Path(directory)
    if not root.is_dir():
        raise LeRobotFormatError(f"{root} is not a folder")
    info = load_info(root)
    tasks = load_tasks(root)
    episodes = load_episodes(root)
    notes: list[str] = []
    columns, image = choose_columns(info, notes)
    table = load_frames(root, info, episodes, columns + ([image] if image else []))
    frames = {
        c: _numpy(table[c], info["features"][c]["shape"], f"{root / 'data'} column {c!r}") for c in columns
    }
    frames.update({c: frames[c].reshape(-1) for c in INDEX_KEYS})  # one number per frame, however stored
    check_frames(root, info, episodes, frames)
    tensors, instructions = _tensors(frames, tasks, root)
    if image is not None:
        pixels = _images(table[image], f"{root / 'data'} column {image!r}")
        if pixels is None:
            notes.append(f"image feature {image!r} left out: its frames are files, not bytes in the data")
        else:
            tensors["image"] = torch.from_numpy(pixels)
    dataset, source = exported_meta(root, tensors, notes)
    if dataset is None:
        camera = image.removeprefix(IMAGE_PREFIX) if image and "image" in tensors else ""
        dataset = DemoDataset.create(tensors, synthesized_meta(instructions, tensors, camera))
    return LeRobotImport(dataset, float(info["fps"]), notes, source)
