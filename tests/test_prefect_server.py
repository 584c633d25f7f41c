"""Against a real Prefect server on loopback: the scheduled `reevaluate` deployment is served by
`capvector schedule`, triggered by `prefect deployment run`, and its new scores land in the catalogue.
A configured but unreachable server is an error naming its address, not a hang.
"""

import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest
from conftest import REPO

from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.errors import CatalogueBusy

DEPLOYMENT = "reevaluate/scheduled-reevaluation"
TERMINAL = {"COMPLETED", "FAILED", "CRASHED", "CANCELLED"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(prefect_home: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env.update(
        PREFECT_HOME=str(prefect_home),
        PREFECT_SERVER_ANALYTICS_ENABLED="false",
        DO_NOT_TRACK="1",
        PREFECT_LOGGING_LEVEL="WARNING",
        CAPVECTOR_QUIET="1",
        **extra,
    )
    return env


def _start(args: list[str], env: dict, log: Path) -> subprocess.Popen:
    """A process in its own session, so that it and its children can be stopped together."""
    return subprocess.Popen(
        args, cwd=REPO, env=env, stdout=log.open("wb"), stderr=subprocess.STDOUT, start_new_session=True
    )


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)


def _wait_for(what: str, condition: Callable[[], object], procs: dict[str, subprocess.Popen], limit_s: float):
    """Poll `condition` until it returns something truthy; fail early when a process we need has died."""
    deadline = time.monotonic() + limit_s
    while True:
        value = condition()
        if value:
            return value
        for name, (proc, log) in procs.items():
            if proc.poll() is not None:
                pytest.fail(
                    f"{name} exited ({proc.returncode}) while waiting for {what}:\n{log.read_text()[-4000:]}"
                )
        if time.monotonic() > deadline:
            logs = "\n".join(f"--- {n}\n{log.read_text()[-3000:]}" for n, (_, log) in procs.items())
            pytest.fail(f"gave up waiting for {what} after {limit_s:.0f} s\n{logs}")
        time.sleep(1.0)


def _get(url: str) -> httpx.Response | None:
    try:
        return httpx.get(url, timeout=10)
    except httpx.HTTPError:
        return None


def _evaluation_counts(home: Path) -> dict[tuple[str, str], int]:
    while True:
        try:
            frame = ArtifactsAPI(str(home)).query(
                "SELECT checkpoint_id, fingerprint, count(DISTINCT evaluation_id) AS n FROM eval_tasks "
                "GROUP BY checkpoint_id, fingerprint"
            )
        except CatalogueBusy:
            continue
        return {(r.checkpoint_id, r.fingerprint): int(r.n) for r in frame.itertuples()}


def test_served_reevaluation_deployment_writes_new_scores(smoke_home, tmp_path):
    home, ids = smoke_home
    port = _free_port()
    api_url = f"http://127.0.0.1:{port}/api"
    prefect = str(Path(sys.executable).parent / "prefect")
    before = _evaluation_counts(home)
    assert (ids["checkpoints"]["capvector/seed0"], _fingerprint(home, ids)) in before

    procs: dict[str, tuple[subprocess.Popen, Path]] = {}
    try:
        server_log = tmp_path / "server.log"
        server = _start(
            [prefect, "server", "start", "--host", "127.0.0.1", "--port", str(port)],
            _env(tmp_path / "prefect-server"),
            server_log,
        )
        procs["prefect server"] = (server, server_log)
        health = _wait_for(
            "the server's /api/health",
            lambda: (r := _get(f"{api_url}/health")) and r.status_code == 200,
            procs,
            300,
        )
        assert health

        client_env = _env(tmp_path / "prefect-client", PREFECT_API_URL=api_url, CAPVECTOR_HOME=str(home))
        serve_log = tmp_path / "serve.log"
        serve = _start(
            [sys.executable, "-m", "capvector", "schedule", "--cron", "0 3 * * *", "--home", str(home)],
            client_env,
            serve_log,
        )
        procs["capvector schedule"] = (serve, serve_log)
        deployment = _wait_for(
            "the deployment to be registered",
            lambda: (
                (r := _get(f"{api_url}/deployments/name/{DEPLOYMENT}")) and r.status_code == 200 and r.json()
            ),
            procs,
            300,
        )
        assert deployment["schedules"][0]["schedule"]["cron"] == "0 3 * * *"
        assert deployment["parameters"]["home"] == str(home)

        triggered = subprocess.run(
            [prefect, "deployment", "run", DEPLOYMENT],
            cwd=REPO,
            env=client_env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert triggered.returncode == 0, triggered.stdout + triggered.stderr
        flow_run_id = re.search(r"UUID:\s*([0-9a-f-]{36})", triggered.stdout).group(1)

        state = _wait_for(
            "the triggered flow run to finish",
            lambda: (
                (r := _get(f"{api_url}/flow_runs/{flow_run_id}"))
                and r.status_code == 200
                and r.json()["state_type"] in TERMINAL
                and r.json()["state_type"]
            ),
            procs,
            600,
        )
        assert state == "COMPLETED", serve_log.read_text()[-4000:]

        # The same checkpoints, protocols and library versions reproduce the same episodes: the same
        # evaluations (content-addressed ids), so nothing new in the store; the run and its summary are.
        assert _evaluation_counts(home) == before
        runs = (
            ArtifactsAPI(str(home))
            .query("SELECT flow_name, state FROM runs WHERE flow_run_id = ?", [flow_run_id])
            .values.tolist()
        )
        assert runs == [["reevaluate", "COMPLETED"]]

        summary = httpx.post(
            f"{api_url}/artifacts/filter",
            json={"artifacts": {"key": {"any_": ["reevaluation-summary"]}}},
            timeout=30,
        )
        assert summary.status_code == 200
        assert any(a["flow_run_id"] == flow_run_id and a["type"] == "markdown" for a in summary.json())
    finally:
        for proc, _ in reversed(procs.values()):
            _stop(proc)


def _fingerprint(home: Path, ids: dict) -> str:
    frame = ArtifactsAPI(str(home)).query(
        "SELECT fingerprint FROM eval_tasks WHERE evaluation_id = ?", [ids["evaluations"]["capvector/seed0"]]
    )
    return str(frame.fingerprint[0])


def test_unreachable_server_fails_fast_naming_the_url(tmp_path):
    url = f"http://127.0.0.1:{_free_port()}/api"  # nothing listens there once the probe socket is closed
    proc = subprocess.run(
        [sys.executable, "-m", "capvector", "run", "--preset", "smoke"],
        cwd=REPO,
        env=_env(tmp_path / "prefect", PREFECT_API_URL=url, CAPVECTOR_HOME=str(tmp_path / "home")),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 2, proc.stderr
    assert url in proc.stderr and "not reachable" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "home").exists()


def test_runs_are_named_and_tagged_and_step_progress_reaches_the_logs(smoke_home, tmp_path):
    """The UI shows `study smoke <id>` (a run is a study) tagged capvector/run/smoke, task runs spelled in
    ASCII (θ → theta), and the progress lines printed inside steps run by pool workers in its Logs tab."""
    home, _ = smoke_home
    port = _free_port()
    api_url = f"http://127.0.0.1:{port}/api"
    prefect = str(Path(sys.executable).parent / "prefect")
    procs: dict[str, tuple[subprocess.Popen, Path]] = {}
    try:
        server_log = tmp_path / "server.log"
        server = _start(
            [prefect, "server", "start", "--host", "127.0.0.1", "--port", str(port)],
            _env(tmp_path / "prefect-server"),
            server_log,
        )
        procs["prefect server"] = (server, server_log)
        healthy = lambda: (r := _get(f"{api_url}/health")) and r.status_code == 200  # noqa: E731
        _wait_for("/api/health", healthy, procs, 300)
        client_env = _env(tmp_path / "prefect-client", PREFECT_API_URL=api_url)
        run = subprocess.run(  # a changed horizon: every evaluation step runs again in a pool worker
            [sys.executable, "-m", "capvector", "run", "--preset", "smoke", "--set", "evaluation.horizon=30",
             "--json", "--home", str(home)],  # fmt: skip
            cwd=REPO,
            env=client_env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert run.returncode == 0, run.stderr[-4000:]
        flows = httpx.post(f"{api_url}/flow_runs/filter", json={}, timeout=30).json()
        (pipeline,) = [f for f in flows if f["name"].startswith("study smoke ")]
        assert {"capvector", "run", "smoke"} <= set(pipeline["tags"])
        tasks = httpx.post(
            f"{api_url}/task_runs/filter", json={"flow_runs": {"id": {"any_": [pipeline["id"]]}}}, timeout=30
        ).json()
        names = [t["name"] for t in tasks]
        assert any("theta" in n for n in names) and not any("θ" in n for n in names)

        def progress() -> list[dict]:
            body = {"logs": {"flow_run_id": {"any_": [pipeline["id"]]}}, "limit": 200}
            logs = httpx.post(f"{api_url}/logs/filter", json=body, timeout=30).json()
            return [g for g in logs if g["task_run_id"] and "episodes" in g["message"]]

        assert _wait_for("a step's progress in the run's logs", progress, procs, 60)
    finally:
        for proc, _ in reversed(procs.values()):
            _stop(proc)
