"""LeRobotDataset v3.0 out and in: `capvector export --format lerobot` and `capvector import-dataset` on
tiny real demos (Meta-World's scripted expert), checked against the v3.0 layout of LeRobot's source
(src/lerobot/datasets/utils.py: meta/info.json, meta/stats.json, meta/tasks.parquet,
meta/episodes/chunk-000/file-000.parquet, data/chunk-000/file-000.parquet) with pandas as the reader.
"""

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import torch
from conftest import run_cli
from typer.testing import CliRunner

from capvector.artifacts.api import ArtifactsAPI
from capvector.core.simulation.demos import DemoConfig, DemoDataset, collect_demos
from capvector.core.simulation.envs import EnvConfig, MetaWorldEnv
from capvector.core.simulation.lerobot_export import data_files, write_lerobot
from capvector.core.simulation.lerobot_import import read_lerobot
from capvector.core.simulation.lerobot_layout import METAWORLD_FPS, LeRobotFormatError
from capvector.flows.cli.main import app
from capvector.tasks.lerobot_dataset import folder_hash

DATA = "data/chunk-000/file-000.parquet"
EPISODES = "meta/episodes/chunk-000/file-000.parquet"


@pytest.fixture(scope="module")
def demos():
    config = DemoConfig(tasks=["reach-v3", "drawer-close-v3"], episodes_per_task=1, horizon=150, workers=1)
    return collect_demos(config)


@pytest.fixture(scope="module")
def pixel_demos():
    config = DemoConfig(
        tasks=["reach-v3"], episodes_per_task=2, horizon=150, workers=1, obs_mode="pixels", image_size=32,
        patch_xyz=True, patch_grid=4,
    )  # fmt: skip
    return collect_demos(config)


@pytest.fixture(scope="module")
def exported(demos, tmp_path_factory):
    return write_lerobot(demos, tmp_path_factory.mktemp("lerobot") / "demos", METAWORLD_FPS)


@pytest.fixture(scope="module")
def pixel_exported(pixel_demos, tmp_path_factory):
    """Written with a 0.05 MB data-file limit: each episode in a data file of its own."""
    return write_lerobot(
        pixel_demos, tmp_path_factory.mktemp("lerobot") / "pixels", METAWORLD_FPS, limit_mb=0.05
    )


def _root(summary):
    return Path(summary["path"])


def _same_bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Exactly equal, NaN included (patch_xyz is NaN where a patch sees no geometry)."""
    return a.dtype == b.dtype and a.shape == b.shape and a.numpy().tobytes() == b.numpy().tobytes()


def test_the_folder_has_the_v3_layout_and_names(exported, demos):
    root = _root(exported)
    files = sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
    assert files == sorted(
        ["meta/info.json", "meta/stats.json", "meta/tasks.parquet", "meta/capvector.json", EPISODES, DATA]
    )
    info = json.loads((root / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 80 and info["robot_type"] == "sawyer"
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["video_path"] is None and info["chunks_size"] == 1000 and info["splits"] == {"train": "0:2"}
    features = info["features"]
    assert features["observation.state"]["dtype"] == "float32" and features["observation.state"]["shape"] == [
        39
    ]
    assert (
        len(features["observation.state"]["names"]) == 39
        and features["observation.state"]["names"][0] == "hand_x"
    )
    assert features["action"] == {
        "dtype": "float32",
        "shape": [4],
        "names": ["delta_x", "delta_y", "delta_z", "gripper"],
    }
    for key, dtype in [("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                       ("index", "int64"), ("task_index", "int64"), ("next.done", "bool")]:  # fmt: skip
        assert features[key] == {"dtype": dtype, "shape": [1], "names": None}, key
    assert features["capvector.privileged"]["shape"] == [9]
    assert "capvector.proprio" not in features  # proprio is state[:4]: derived on import, not written
    assert not any(k.startswith("observation.images.") for k in features)  # state demos hold no image


def test_info_totals_match_the_files(exported, demos):
    root = _root(exported)
    info = json.loads((root / "meta/info.json").read_text())
    assert info["total_episodes"] == demos.meta.n_episodes == 2
    assert info["total_frames"] == len(demos) and info["total_tasks"] == 2
    data = pd.read_parquet(root / DATA)
    assert len(data) == info["total_frames"] and list(data.columns) == list(info["features"])
    episodes = pd.read_parquet(root / EPISODES)
    assert episodes["length"].sum() == info["total_frames"] and episodes["episode_index"].tolist() == [0, 1]
    assert episodes["dataset_from_index"].tolist() == [0, episodes["length"][0]]
    assert episodes["dataset_to_index"].tolist() == episodes["length"].cumsum().tolist()
    assert (episodes["data/chunk_index"] == 0).all() and (episodes["data/file_index"] == 0).all()
    assert [list(t) for t in episodes["tasks"]] == [[text] for text in demos.meta.instructions]
    tasks = pd.read_parquet(root / "meta/tasks.parquet")  # as LeRobot reads it: the text is the index
    assert tasks.index.name == "task" and list(tasks.index) == demos.meta.instructions
    assert tasks["task_index"].tolist() == [0, 1] and tasks.iloc[1].name == "push the drawer closed"
    state = np.stack(data["observation.state"].to_numpy())
    assert np.array_equal(state, demos.tensors["state"].numpy())
    assert data["next.done"].sum() == 2 and data["next.done"].iloc[-1]
    assert np.allclose(data["timestamp"], data["frame_index"] / 80)
    assert data["index"].tolist() == list(range(len(demos)))


def test_stats_per_numeric_feature(exported, pixel_exported, demos, pixel_demos):
    stats = json.loads((_root(exported) / "meta/stats.json").read_text())
    action = demos.tensors["action"].double()
    assert set(stats["action"]) >= {"min", "max", "mean", "std", "count"}
    assert stats["action"]["count"] == [len(demos)]
    assert np.allclose(stats["action"]["mean"], action.mean(0)) and np.allclose(
        stats["action"]["max"], action.amax(0)
    )
    assert np.allclose(stats["action"]["std"], action.std(0, unbiased=False))
    assert stats["frame_index"]["min"] == [0] and stats["episode_index"]["max"] == [1]
    pixel = json.loads((_root(pixel_exported) / "meta/stats.json").read_text())
    image = pixel["observation.images.corner2"]
    assert np.array(image["mean"]).shape == (3, 1, 1) and image["count"] == [len(pixel_demos)]
    means = pixel_demos.tensors["image"].double().mean((0, 1, 2)) / 255
    assert np.allclose(np.array(image["mean"]).ravel(), means)


def test_every_parquet_written_reads_with_pandas(exported, pixel_exported):
    for summary in (exported, pixel_exported):
        for path in sorted(_root(summary).rglob("*.parquet")):
            frame = pd.read_parquet(path)
            assert len(frame) > 0, path


def test_round_trip_is_exact(exported, demos):
    back = read_lerobot(_root(exported))
    assert back.notes == [] and back.fps == 80
    assert back.dataset.meta == demos.meta and back.dataset.content_hash == demos.content_hash
    assert set(back.dataset.tensors) == set(demos.tensors)
    for key, tensor in demos.tensors.items():
        assert torch.equal(back.dataset.tensors[key], tensor), key


def test_pixels_round_trip_across_data_files(pixel_exported, pixel_demos):
    root = _root(pixel_exported)
    assert pixel_exported["data_files"] == 2  # the 0.05 MB limit puts each episode in a file of its own
    assert sorted(p.relative_to(root).as_posix() for p in root.glob("data/*/*")) == [
        "data/chunk-000/file-000.parquet",
        "data/chunk-000/file-001.parquet",
    ]
    assert pd.read_parquet(root / EPISODES)["data/file_index"].tolist() == [0, 1]
    info = json.loads((root / "meta/info.json").read_text())
    assert info["features"]["observation.images.corner2"] == {
        "dtype": "image", "shape": [32, 32, 3], "names": ["height", "width", "channels"]
    }  # fmt: skip
    assert info["features"]["capvector.patch_xyz"]["shape"] == [16, 3]
    back = read_lerobot(root)
    assert back.dataset.content_hash == pixel_demos.content_hash and back.dataset.meta == pixel_demos.meta
    assert set(back.dataset.tensors) == set(pixel_demos.tensors)
    for key, tensor in pixel_demos.tensors.items():
        assert _same_bits(back.dataset.tensors[key], tensor), key


def test_data_files_never_split_an_episode():
    bounds = [(0, 5), (5, 15), (15, 18), (18, 30)]
    assert data_files(bounds, 1024 * 1024, 8) == [[0], [1], [2], [3]]  # one MB a frame: every episode alone
    assert data_files(bounds, 1024, 10 / 1024) == [[0], [1], [2], [3]]  # 10 frames a file
    assert data_files(bounds, 1024, 18 / 1024) == [[0, 1, 2], [3]]
    assert data_files(bounds, 1, 100) == [[0, 1, 2, 3]]


def test_a_folder_capvector_did_not_write_gets_its_meta_from_the_folder(exported, demos, tmp_path):
    root = shutil.copytree(_root(exported), tmp_path / "foreign")
    (root / "meta/capvector.json").unlink()
    back = read_lerobot(root)
    meta = back.dataset.meta
    assert meta.tasks == ["reach-v3", "drawer-close-v3"]  # capvector's instruction texts: named back
    assert meta.instructions == demos.meta.instructions and meta.seeds == {} and meta.obs_mode == "state"
    assert (
        meta.n_episodes == 2
        and meta.n_steps == len(demos)
        and meta.horizon == int(demos.tensors["step"].max()) + 1
    )
    for key, tensor in demos.tensors.items():
        assert torch.equal(back.dataset.tensors[key], tensor), key
    assert back.dataset.content_hash != demos.content_hash  # another meta: another dataset
    stale = json.loads((_root(exported) / "meta/capvector.json").read_text())
    stale["dataset"]["camera"] = "corner3"  # no longer what the data hash to
    (root / "meta/capvector.json").write_text(json.dumps(stale))
    back = read_lerobot(root)
    assert back.source_artifact is None and "describes other data" in back.notes[0]
    assert back.dataset.meta.seeds == {}


def test_a_folder_written_by_pandas_as_another_tool_would(tmp_path):
    """Lists of float64 (as pandas writes them), a video feature and a reward: state, action, episodes and
    the task text are read; the video and the reward are named in the notes."""
    root = tmp_path / "other"
    lengths, n = [3, 2], 5
    state = np.arange(n * 6, dtype=np.float64).reshape(n, 6) / 7
    action = -np.arange(n * 2, dtype=np.float64).reshape(n, 2) / 3
    (root / "data/chunk-000").mkdir(parents=True)
    (root / "meta/episodes/chunk-000").mkdir(parents=True)
    pd.DataFrame(
        {
            "observation.state": list(state),
            "action": list(action),
            "next.reward": np.ones(n),
            "timestamp": [0.0, 0.1, 0.2, 0.0, 0.1],
            "frame_index": [0, 1, 2, 0, 1],
            "episode_index": [0, 0, 0, 1, 1],
            "index": list(range(n)),
            "task_index": [0, 0, 0, 0, 0],
        }
    ).to_parquet(root / DATA)
    pd.DataFrame(
        {
            "episode_index": [0, 1],
            "tasks": [["Reach a goal position"]] * 2,
            "length": lengths,
            "data/chunk_index": [0, 0],
            "data/file_index": [0, 0],
            "dataset_from_index": [0, 3],
            "dataset_to_index": [3, 5],
        }
    ).to_parquet(root / EPISODES)
    pd.DataFrame({"task_index": [0]}, index=pd.Index(["Reach a goal position"], name="task")).to_parquet(
        root / "meta/tasks.parquet"
    )
    scalar = {"shape": [1], "names": None}
    features = {
        "observation.state": {"dtype": "float64", "shape": [6], "names": None},
        "action": {"dtype": "float64", "shape": [2], "names": None},
        "observation.images.top": {"dtype": "video", "shape": [480, 480, 3], "names": None},
        "next.reward": {"dtype": "float64", **scalar},
        "timestamp": {"dtype": "float32", **scalar},
        **{k: {"dtype": "int64", **scalar} for k in ("frame_index", "episode_index", "index", "task_index")},
    }
    info = {
        "codebase_version": "v3.0",
        "fps": 10,
        "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "total_episodes": 2,
        "total_frames": n,
        "features": features,
    }
    (root / "meta/info.json").write_text(json.dumps(info))
    back = read_lerobot(root)
    t, meta = back.dataset.tensors, back.dataset.meta
    assert back.fps == 10 and meta.tasks == meta.instructions == ["Reach a goal position"]
    assert torch.equal(t["state"], torch.from_numpy(state.astype(np.float32)))
    assert torch.equal(t["action"], torch.from_numpy(action.astype(np.float32)))
    assert torch.equal(t["proprio"], t["state"][:, :4]) and "image" not in t and meta.obs_mode == "state"
    assert t["episode"].tolist() == [0, 0, 0, 1, 1] and t["step"].tolist() == [0, 1, 2, 0, 1]
    assert meta.n_episodes == 2 and meta.horizon == 3 and meta.episodes_per_task == 2
    assert any("observation.images.top" in note and "video" in note for note in back.notes)
    assert any("next.reward" in note for note in back.notes)


def _edit_json(path, change):
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def _drop_column(path, column):
    table = pq.read_table(path)
    pq.write_table(table.drop_columns([column]), path)


BAD_FOLDERS = {
    "no info": (lambda r: (r / "meta/info.json").unlink(), r"meta/info\.json is missing"),
    "not json": (lambda r: (r / "meta/info.json").write_text("{"), r"info\.json is not valid JSON"),
    "v2.1": (
        lambda r: _edit_json(r / "meta/info.json", lambda i: i.update(codebase_version="v2.1")),
        r"info\.json: codebase_version is 'v2\.1', not 'v3\.0'",
    ),
    "no state": (
        lambda r: _edit_json(r / "meta/info.json", lambda i: i["features"].pop("observation.state")),
        r"info\.json: features has no 'observation\.state'",
    ),
    "no action": (
        lambda r: _edit_json(r / "meta/info.json", lambda i: i["features"].pop("action")),
        r"info\.json: features has no 'action'",
    ),
    "no tasks": (lambda r: (r / "meta/tasks.parquet").unlink(), r"meta/tasks\.parquet is missing"),
    "no episodes": (lambda r: shutil.rmtree(r / "meta/episodes"), r"meta/episodes holds no chunk-\*/file-\*"),
    "action column": (
        lambda r: _drop_column(r / DATA, "action"),
        r"file-000\.parquet has no column\(s\) \['action'\]",
    ),
    "episode column": (
        lambda r: _drop_column(r / EPISODES, "dataset_from_index"),
        r"episodes/chunk-000/file-000\.parquet has no column\(s\) \['dataset_from_index'\]",
    ),
    "no data": (lambda r: (r / DATA).unlink(), r"data/chunk-000/file-000\.parquet is missing"),
    "totals": (
        lambda r: _edit_json(r / "meta/info.json", lambda i: i.update(total_frames=3)),
        r"info\.json: total_frames is 3, the folder holds",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_FOLDERS))
def test_bad_folders_are_refused_naming_file_and_field(exported, tmp_path, case):
    root = shutil.copytree(_root(exported), tmp_path / case)
    damage, message = BAD_FOLDERS[case]
    damage(root)
    with pytest.raises(LeRobotFormatError, match=message):
        read_lerobot(root)


def test_export_writes_only_a_new_folder(demos, tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not an empty folder"):
        write_lerobot(demos, tmp_path / "full", METAWORLD_FPS)
    assert [p.name for p in tmp_path.iterdir()] == ["full"]  # no staged folder left behind
    (tmp_path / "empty").mkdir()
    assert write_lerobot(demos, tmp_path / "empty", METAWORLD_FPS)["total_frames"] == len(demos)


def test_metaworld_runs_at_the_fps_written():
    with MetaWorldEnv(EnvConfig(task="reach-v3")) as env:
        assert round(1 / env.env.dt) == METAWORLD_FPS


def test_cli_export_then_import_keeps_lineage(demos, tmp_path):
    home = tmp_path / "home"
    api = ArtifactsAPI(str(home))
    saved = demos.save(tmp_path / "saved")
    original = api.register_dir(saved, kind="dataset", name="demos").id
    checkpoint = api.register_json({"w": 1}, "checkpoint", "not a dataset").id
    runner = CliRunner()
    out = tmp_path / "out"
    export = [
        "--home",
        str(home),
        "export",
        "--format",
        "lerobot",
        str(out),
        "--dataset",
        original[:12],
        "--json",
    ]
    written = json.loads(runner.invoke(app, export, catch_exceptions=False).stdout)
    assert written["dataset"] == original and written["total_frames"] == len(demos)
    assert (out / "meta/info.json").is_file()
    result = runner.invoke(
        app, ["--home", str(home), "import-dataset", str(out), "--json"], catch_exceptions=False
    )
    imported = json.loads(result.stdout)
    assert imported["id"] != original and imported["name"] == "lerobot out" and imported["notes"] == []
    source = imported["config"]["imported_from"]
    assert source["format"] == "LeRobotDataset v3.0" and source["path"] == str(out.resolve())
    assert (
        source["folder_hash"] == folder_hash(out) == api.register_dir(out, kind="folder", name="as stored").id
    )
    again = runner.invoke(
        app, ["--home", str(home), "import-dataset", str(out), "--json"], catch_exceptions=False
    )
    assert json.loads(again.stdout)["id"] == imported["id"]  # the same folder: the same artifact
    record = api.get(imported["id"])
    assert record.kind == "dataset" and [(p.id, p.role) for p in record.parents] == [(original, "source")]
    back = DemoDataset.load(api.path(record.id, verify=True))
    assert back.content_hash == demos.content_hash
    refused = run_cli(
        "export", "--format", "lerobot", str(tmp_path / "x"), "--dataset", checkpoint, home=home, check=False
    )
    assert refused.returncode == 2 and "is a checkpoint artifact" in refused.stderr, refused.stderr
    (out / "meta/info.json").unlink()
    refused = run_cli("import-dataset", str(out), home=home, check=False)
    assert refused.returncode == 2 and "meta/info.json is missing" in refused.stderr, refused.stderr
    missing = runner.invoke(app, ["--home", str(home), "export", "--format", "lerobot", str(tmp_path / "y")])
    assert missing.exit_code == 2 and "give --dataset ID" in missing.output
