"""Run logs and Prefect's run history stay bounded (issue 27, item 4); nothing else is touched.

The log tests are plain files (milliseconds). The Prefect test runs one subprocess on a fresh
PREFECT_HOME: a tiny @flow five times on Prefect's embedded server, then `capvector catalogue
housekeeping` in the same process (so the server boots once). That boot is most of its 18-23 s on a busy
2-core machine; the pruning itself takes well under a second.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

from typer.testing import CliRunner

from capvector.flows.cli.catalogue_commands import catalogue_app
from capvector.flows.runtime.housekeeping import ACTIVE_S, logs_dir, prune_logs, prune_on_start
from capvector.tasks.runtime.workspace import Workspace

REPO = Path(__file__).resolve().parent.parent
DAY = 86400.0


def _home_with_an_artifact(tmp_path: Path) -> Path:
    """A home with a stored artifact, its catalogue row and the folders a run leaves beside its logs."""
    home = tmp_path / "home"
    workspace = Workspace(str(home))
    src = tmp_path / "weights.bin"
    src.write_bytes(b"\x00" * 4096)
    workspace.api.register_file(src, kind="checkpoint", name="kept")
    for folder in ("step-cache", "locks", "work", "reports"):
        (home / folder).mkdir(parents=True, exist_ok=True)
        (home / folder / "old.log").write_text("not a run log")  # a .log outside logs/: never a candidate
        os.utime(home / folder / "old.log", (time.time() - 400 * DAY,) * 2)
    return home


def _logs(home: Path, ages_days: list[float], size: int = 1000) -> list[Path]:
    """Log files aged as given (index 0 the oldest when ages decrease), named by age rank."""
    folder = logs_dir(str(home))
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    now = time.time()
    for i, age in enumerate(ages_days):
        path = folder / f"run-smoke-{i:03d}.log"
        path.write_bytes(b"x" * size)
        os.utime(path, (now - age * DAY, now - age * DAY))
        paths.append(path)
    return paths


def _everything_but_logs(home: Path) -> dict[str, tuple[int, int]]:
    """Every file of the home outside logs/ with its size and mtime: what housekeeping must not touch."""
    return {
        str(p.relative_to(home)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(home.rglob("*"))
        if p.is_file() and "logs" not in p.relative_to(home).parts
    }


def test_logs_beyond_the_age_count_and_size_limits_go_oldest_first(tmp_path):
    home = _home_with_an_artifact(tmp_path)
    before = _everything_but_logs(home)
    n_artifacts = len(list(Workspace(str(home)).api.store.iter_ids()))
    paths = _logs(home, [50, 40, 31, 20, 10, 5, 3, 2, 1])  # oldest first

    by_age = prune_logs(str(home), keep_days=30, keep_files=None, keep_bytes=None)
    assert [f.path for f in by_age.deleted] == paths[:3]  # older than 30 days, oldest first
    assert [p.exists() for p in paths] == [False] * 3 + [True] * 6

    by_count = prune_logs(str(home), keep_days=None, keep_files=4, keep_bytes=None)
    assert [f.path for f in by_count.deleted] == paths[3:5]
    assert by_count.kept == 4

    by_size = prune_logs(str(home), keep_days=None, keep_files=None, keep_bytes=2500)
    assert [f.path for f in by_size.deleted] == paths[5:7]  # the two newest (2000 bytes) fit
    assert sorted(p.name for p in logs_dir(str(home)).iterdir()) == [p.name for p in paths[7:]]

    assert _everything_but_logs(home) == before  # store, catalogue, cache, locks, work, reports
    assert len(list(Workspace(str(home)).api.store.iter_ids())) == n_artifacts
    rows = Workspace(str(home)).api.query_rows("SELECT count(*) FROM artifacts")[1]
    assert rows[0][0] == n_artifacts


def test_a_limit_reached_removes_every_older_log_never_a_hole(tmp_path):
    home = tmp_path / "home"
    folder = logs_dir(str(home))
    folder.mkdir(parents=True)
    now = time.time()
    for name, size, age in [("new.log", 100, 1), ("big.log", 5000, 2), ("small-old.log", 10, 3)]:
        (folder / name).write_bytes(b"x" * size)
        os.utime(folder / name, (now - age * DAY,) * 2)
    report = prune_logs(str(home), keep_days=None, keep_files=None, keep_bytes=1000)
    assert [f.path.name for f in report.deleted] == ["small-old.log", "big.log"]  # oldest first
    assert [p.name for p in folder.iterdir()] == ["new.log"]


def test_running_logs_links_and_other_files_are_never_deleted(tmp_path, monkeypatch):
    home = tmp_path / "home"
    paths = _logs(home, [90, 80, 0])
    folder = logs_dir(str(home))
    os.utime(paths[2], (time.time() - ACTIVE_S / 2,) * 2)  # still being written by a run
    monkeypatch.setenv("CAPVECTOR_LOG_FILE", str(paths[1]))  # this process's own log
    outside = tmp_path / "precious.log"
    outside.write_text("mine")
    os.utime(outside, (time.time() - 400 * DAY,) * 2)
    (folder / "link.log").symlink_to(outside)
    (folder / "notes.txt").write_text("kept")
    os.utime(folder / "notes.txt", (time.time() - 400 * DAY,) * 2)

    report = prune_logs(str(home), keep_days=1, keep_files=0, keep_bytes=0)
    assert [f.path for f in report.deleted] == [paths[0]]
    assert paths[1].exists() and paths[2].exists()
    assert outside.read_text() == "mine" and (folder / "link.log").is_symlink()
    assert (folder / "notes.txt").exists()


def test_dry_run_deletes_nothing_and_the_command_says_what_it_would(tmp_path):
    home = _home_with_an_artifact(tmp_path)
    before = _everything_but_logs(home)
    paths = _logs(home, [100, 60, 1])
    folder = logs_dir(str(home))
    listing = sorted(folder.iterdir())

    report = prune_logs(str(home), keep_days=30, dry_run=True)
    assert [f.path for f in report.deleted] == paths[:2]
    assert sorted(folder.iterdir()) == listing

    runner = CliRunner()
    args = ["housekeeping", "--no-runs", "--home", str(home), "--logs-older-than", "30"]
    dry = runner.invoke(catalogue_app, [*args, "--dry-run"])
    assert dry.exit_code == 0, dry.output
    assert "would delete 2" in dry.output and str(paths[0]) in dry.output
    assert sorted(folder.iterdir()) == listing

    done = runner.invoke(catalogue_app, [*args, "--json"])
    assert done.exit_code == 0, done.output
    assert json.loads(done.output)["logs"]["deleted"] == [str(p) for p in paths[:2]]
    assert sorted(folder.iterdir()) == [paths[2]]
    assert _everything_but_logs(home) == before


def test_prune_on_start_keeps_the_default_bound_and_never_fails(tmp_path):
    home = tmp_path / "home"
    paths = _logs(home, [45] + [1 + i / 1000 for i in range(210)][::-1])  # 1 too old, 210 recent
    report = prune_on_start(str(home))
    assert report is not None and report.kept == 200
    assert not paths[0].exists()  # older than 30 days
    assert [p.exists() for p in paths[1:]] == [False] * 10 + [True] * 200  # the 10 oldest of 210
    assert prune_on_start(str(tmp_path / "no-such-home")) is not None  # no logs yet: nothing to do
    (tmp_path / "file-home").write_text("")
    assert prune_on_start(str(tmp_path / "file-home")) is None  # an unusable home does not raise


PREFECT_SCRIPT = textwrap.dedent(
    """
    import json, sys
    from datetime import UTC, datetime, timedelta

    from prefect import flow, task
    from prefect.artifacts import create_markdown_artifact
    from prefect.client.orchestration import get_client
    from prefect.logging import get_run_logger
    from prefect.logging.handlers import APILogHandler
    from typer.testing import CliRunner

    from capvector.flows.cli.catalogue_commands import catalogue_app
    from capvector.flows.runtime.housekeeping import prune_prefect_db

    @task
    def step(i):
        return i

    @flow(name="pipeline", persist_result=False)
    def tiny(i: int):
        get_run_logger().warning("run %s", i)
        create_markdown_artifact(markdown=f"# {i}", key=f"tiny-{i}")
        return step(i)

    @flow(name="someone-elses-flow", persist_result=False)
    def other():
        return 1

    for i in range(5):
        tiny(i)
    other()
    APILogHandler().flush()  # the runs' log lines reach the server before anything is counted

    def names():
        with get_client(sync_client=True) as client:
            return sorted(r.name for r in client.read_flow_runs())

    def logs():
        with get_client(sync_client=True) as client:
            return sorted(str(log.flow_run_id) for log in client.read_logs())

    out = {"made": names(), "logs_before": logs()}
    cli = CliRunner()
    dry = cli.invoke(catalogue_app, ["housekeeping", "--no-logs", "--keep-runs", "2", "--dry-run", "--json"])
    out["dry"] = json.loads(dry.output)["runs"]
    out["after_dry"] = names()
    done = cli.invoke(catalogue_app, ["housekeeping", "--no-logs", "--keep-runs", "2", "--json"])
    out["count"] = json.loads(done.output)["runs"]
    out["after_count"] = names()
    with get_client(sync_client=True) as client:
        out["task_runs"] = len(client.read_task_runs())
        out["artifacts"] = len(client.read_artifacts())
    out["logs"] = logs()
    later = datetime.now(UTC) + timedelta(days=31)  # the two kept runs, a month later
    out["age"] = prune_prefect_db(older_than_days=30, keep_runs=None, now=later).as_dict()
    out["after_age"] = names()
    print(json.dumps(out, default=str))
    """
)


def test_prefect_pruning_removes_old_runs_with_their_task_runs_logs_and_artifacts(tmp_path):
    env = {
        **os.environ,
        "PREFECT_HOME": str(tmp_path / "prefect"),
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "DO_NOT_TRACK": "1",
        "PREFECT_LOGGING_LEVEL": "WARNING",
    }
    env.pop("PREFECT_API_URL", None)
    proc = subprocess.run(
        [sys.executable, "-c", PREFECT_SCRIPT], cwd=REPO, env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    made = out["made"]
    assert len(made) == 6

    dry = out["dry"]
    assert dry["dry_run"] and len(dry["deleted"]) == 3 and dry["kept"] == 2
    assert out["after_dry"] == made  # a dry run deletes nothing

    count = out["count"]
    # the three oldest runs of capvector's flows go; the other project's flow is never touched
    assert [r["name"] for r in count["deleted"]] == [r["name"] for r in dry["deleted"]]
    assert all(r["flow"] == "pipeline" for r in count["deleted"])
    assert count["artifacts_deleted"] == 3 and count["logs_pending"] == 0
    kept = sorted(set(made) - {r["name"] for r in count["deleted"]})
    assert out["after_count"] == kept and len(kept) == 3
    assert out["task_runs"] == 2  # one per kept pipeline run: the deleted runs' went with them
    assert out["artifacts"] == 2
    deleted_ids = {r["id"] for r in count["deleted"]}
    assert deleted_ids <= set(out["logs_before"])  # the deleted runs had log lines ...
    assert out["logs"] == [i for i in out["logs_before"] if i not in deleted_ids]  # ... and have none now

    assert count["database"].startswith(str(tmp_path / "prefect"))
    assert count["vacuum"] == "done" and count["bytes_after"] <= count["bytes_before"]

    age = out["age"]
    assert len(age["deleted"]) == 2 and age["kept"] == 0
    assert len(out["after_age"]) == 1  # only the other flow's run is left
