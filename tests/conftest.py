"""Shared test settings: offscreen rendering, no telemetry, a private Prefect home per session."""

import atexit
import os
import shutil
import tempfile

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] = "false"
os.environ["DO_NOT_TRACK"] = "1"
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")  # loaded CI machines
for _name in ("CAPVECTOR_SCRATCH", "CAPVECTOR_CACHE"):  # a developer's own settings must not leak in
    os.environ.pop(_name, None)
# One per test process, made once although pytest imports this file under two names, and removed when
# the process ends (each holds a Prefect database: they piled up in /tmp, about 3 MB a process).
_home_made_here = os.environ.get("CAPVECTOR_TEST_PREFECT_HOME_OF") == str(os.getpid())
if "CAPVECTOR_TEST_KEEP_PREFECT_HOME" not in os.environ and not _home_made_here:
    os.environ["PREFECT_HOME"] = tempfile.mkdtemp(prefix="capvector-prefect-")
    os.environ["CAPVECTOR_TEST_PREFECT_HOME_OF"] = str(os.getpid())
    atexit.register(shutil.rmtree, os.environ["PREFECT_HOME"], ignore_errors=True)

# One Prefect API server per test process (each pytest-xdist worker has its own PREFECT_HOME), which
# every `capvector` the tests start is told about through PREFECT_API_URL, as a user with a running
# `prefect server start` would: a flow command then checks that server instead of booting its own
# (about 11 s of CPU each, the largest fixed cost of a small run). Its URL is exported now, before
# anything imports Prefect, which reads it at import; the process starts with the session
# (`session_prefect_server`). Tests of the CLI's own server pass `own_server_env`. A server named by the
# developer's PREFECT_API_URL is used as it is; one a parent test process reserved (pytest-xdist's
# controller, whose workers inherit its environment) is not this process's to use.
from capvector.flows.runtime.prefect_server import RunServer  # noqa: E402

SESSION_SERVER: RunServer | None = None  # in the copy pytest imports (`from conftest import` makes another)
_reserved_by = os.environ.get("CAPVECTOR_TEST_SERVER_OF")
if _reserved_by != str(os.getpid()) and (_reserved_by or not os.environ.get("PREFECT_API_URL")):
    SESSION_SERVER = RunServer()
    os.environ["PREFECT_API_URL"] = SESSION_SERVER.url
    os.environ["CAPVECTOR_TEST_SERVER_OF"] = str(os.getpid())

import torch  # noqa: E402

# two pytest-xdist workers share the 2 cores of the machine the suite is sized for
torch.set_num_threads(1 if os.environ.get("PYTEST_XDIST_WORKER") else 2)


import fcntl  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
TESTS = REPO / "tests"


def run_in_session(
    argv: list[str], env: dict[str, str], timeout: float, while_running=None
) -> subprocess.CompletedProcess:
    """`argv` in a session of its own, output through files, not pipes; the session's leftovers are
    killed afterwards: a grandchild that outlives the command (Prefect's embedded API server on its way
    down) must neither keep the test waiting for end-of-file nor linger. `while_running(proc)` is
    called once the command has started (a test that interferes with the run: kills a worker)."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(argv, cwd=REPO, env=env, stdout=out, stderr=err, start_new_session=True)
        try:
            if while_running is not None:
                while_running(proc)
            code = proc.wait(timeout=timeout)
        finally:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        out.seek(0)
        err.seek(0)
        return subprocess.CompletedProcess(argv, code, out.read(), err.read())


def own_server_env(env: dict[str, str]) -> dict[str, str]:
    """`env` without the session's Prefect server: a `capvector` started with it boots its own, as on a
    user's machine with no server configured (the tests of that server's life need it)."""
    if not env.get("CAPVECTOR_TEST_SERVER_OF"):  # a server the developer named is theirs
        return dict(env)
    return {k: v for k, v in env.items() if k not in ("PREFECT_API_URL", "CAPVECTOR_TEST_SERVER_OF")}


@pytest.fixture(scope="session", autouse=True)
def session_prefect_server():
    """The session's Prefect API server (SESSION_SERVER), up before the first test; stopped at the end."""
    if SESSION_SERVER is None:
        yield None
        return
    SESSION_SERVER.wait_ready()
    yield SESSION_SERVER
    SESSION_SERVER.stop()


def run_cli(
    *args: str,
    home: Path,
    check: bool = True,
    timeout: float = 900,
    env: dict[str, str] | None = None,
    while_running=None,
) -> subprocess.CompletedProcess:
    """The real console entry point in a subprocess, as a user runs it (`run_in_session`)."""
    env = {**os.environ, "CAPVECTOR_HOME": str(home), "CAPVECTOR_QUIET": "1", **(env or {})}
    result = run_in_session([sys.executable, "-m", "capvector", *args], env, timeout, while_running)
    if check and result.returncode != 0:
        raise AssertionError(
            f"capvector {' '.join(args)} failed ({result.returncode}):\n{result.stderr[-3000:]}"
        )
    return result


def settled_task_states(flow_run_id, timeout: float = 60) -> dict[str, str]:
    """Task-run name -> state name of a finished flow run, once Prefect has recorded every final state:
    the API records task-run states from events, after the flow run has returned, so a read right away
    can still see a cached task as Running, or a task run with no state yet (both seen on CI)."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId

    deadline = time.monotonic() + timeout
    of_this_run = FlowRunFilter(id=FlowRunFilterId(any_=[flow_run_id]))
    with get_client(sync_client=True) as client:
        while True:
            runs = client.read_task_runs(flow_run_filter=of_this_run)
            if all(run.state is not None and run.state.is_final() for run in runs):
                return {run.name: run.state.name for run in runs}
            if time.monotonic() > deadline:  # a task run with no state recorded yet reads as None
                return {run.name: run.state.name if run.state else None for run in runs}
            time.sleep(0.5)


def old_report(workspace, evaluations: dict[str, str]) -> str:
    """A `report` artifact as `capvector run` wrote it before the recipe run once became a study: its
    writer is gone, its records stay readable (`capvector report ID`). One row per arm ("<arm>/seed<k>"
    labels) from the evaluations' scores, each run's lr and parameters from its checkpoint's record."""
    from capvector.artifacts.scores import read_scores
    from capvector.tasks.steps import reporting as r

    scores = {s.evaluation_id: s for s in read_scores(workspace.api, evaluations=evaluations.values())}
    runs: dict[str, list[r.ReportRun]] = {}
    for label, eval_id in sorted(evaluations.items()):
        score, checkpoint = scores[eval_id], workspace.api.get(scores[eval_id].checkpoint_id)
        run = r.ReportRun(
            label=label,
            evaluation_id=eval_id,
            checkpoint_id=checkpoint.id,
            success_rates=score.success_rates,
            mean_success=score.mean_success,
            trainable_parameters=checkpoint.config.get("summary", {}).get("trainable_parameters"),
            lr=r.trained_with(checkpoint.config, "lr"),
        )
        runs.setdefault(label.split("/")[0], []).append(run)
    arms = {
        arm: r.ArmRow(
            overall=r.MeanStd.of([run.mean_success for run in rows]),
            per_task={t: r.MeanStd.of([run.success_rates[t] for run in rows]) for t in rows[0].success_rates},
            trainable_parameters=rows[0].trainable_parameters,
            lr=rows[0].lr,
            runs=rows,
        )
        for arm, rows in runs.items()
    }
    report = r.Report(fingerprint=next(iter(scores.values())).fingerprint, arms=arms)
    report.markdown = r.markdown_table(report)
    parents = [(eval_id, "evaluation") for eval_id in evaluations.values()]
    return workspace.api.register_json(report, kind="report", name="report", parents=parents).id


def _shared_root(tmp_path_factory) -> Path:
    """The folder every pytest-xdist worker of this session sees (its base temp's parent under xdist)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def _smoke_run(tmp_path_factory) -> tuple[Path, dict]:
    """The session's one cold `capvector run --preset smoke`: its home, which no test writes, and its
    `--json`. The first pytest-xdist worker to ask runs it under a lock in the workers' shared temp
    folder; the others wait for it and read what it printed."""
    root = _shared_root(tmp_path_factory)
    shared, done = root / "smoke-home-shared", root / "smoke-home-shared.json"
    with open(root / "smoke-home-shared.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, also if this worker dies
        if not done.exists():
            shutil.rmtree(shared, ignore_errors=True)  # a run that failed in another worker
            proc = run_cli("run", "--preset", "smoke", "--json", home=shared)
            json.loads(proc.stdout)  # the other workers read the run's whole `--json`
            done.write_text(proc.stdout)
    return shared, json.loads(done.read_text())


def smoke_copy(tmp_path_factory, home: Path) -> dict:
    """A copy of the session's smoke run at `home` (made now), and the run's ids, its `report_file`
    pointing into the copy."""
    shared, ids = _smoke_run(tmp_path_factory)
    shutil.copytree(shared, home, dirs_exist_ok=True)
    ids["report_file"] = str(home / Path(ids["report_file"]).relative_to(shared))
    return ids


@pytest.fixture(scope="session")
def smoke_home(tmp_path_factory) -> tuple[Path, dict]:
    """A finished `capvector run --preset smoke` (the recipe as the smallest study) shared by the flow,
    CLI and scheduling tests of one worker; its `--json`: the products' ids and the study's. The run
    happens once per session (`_smoke_run`); each worker gets a copy of its own, since tests add
    evaluations and runs to it and two workers' tests must not write one home at once."""
    home = tmp_path_factory.mktemp("smoke-home")
    return home, smoke_copy(tmp_path_factory, home)


@pytest.fixture
def fresh_smoke_home(tmp_path_factory, tmp_path) -> tuple[Path, dict]:
    """Like `smoke_home`, but a copy of the run no other test has written to."""
    home = tmp_path / "fresh-smoke-home"
    return home, smoke_copy(tmp_path_factory, home)


@pytest.fixture(scope="session")
def s3_endpoint():
    """A moto S3 server on loopback; botocore (hence s3fs) finds it through AWS_ENDPOINT_URL."""
    pytest.importorskip("moto.server")
    s3fs = pytest.importorskip("s3fs")
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.WARNING)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    env = {
        "AWS_ENDPOINT_URL": f"http://{host}:{port}",
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_DEFAULT_REGION": "us-east-1",
    }
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    s3fs.S3FileSystem.clear_instance_cache()
    try:
        yield env["AWS_ENDPOINT_URL"]
    finally:
        s3fs.S3FileSystem.clear_instance_cache()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        server.stop()


@pytest.fixture(scope="module")
def cluster(tmp_path_factory, s3_endpoint):
    """(scheduler address, {worker address: log}, GPU worker address): a scheduler and two workers,
    which reach the loopback S3 server (its address and keys are in their environment). One per test
    module: a module that kills a driver leaves no task of it running on another module's workers."""
    from distributed import Client
    from loopback_cluster import free_port, start, stop  # it imports this module: imported when used

    root = tmp_path_factory.mktemp("dask-cluster")
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    worker_args = ["worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard"]
    scheduler = ["dask", "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"]
    procs = [start(scheduler, root, "scheduler")]
    try:
        for name, extra in (("gpu-worker", ["--resources", "GPU=1"]), ("cpu-worker", [])):
            argv = ["dask", *worker_args, "--local-directory", str(root / name), *extra]
            procs.append(start(argv, root, name))
        deadline = time.monotonic() + 120
        with Client(address, timeout=120) as client:
            while len(client.scheduler_info()["workers"]) < 2:
                dead = [log for proc, log in procs if proc.poll() is not None]
                if dead or time.monotonic() > deadline:
                    pytest.fail(
                        "dask cluster did not start:\n" + "\n".join(p.read_text()[-2000:] for p in dead)
                    )
                time.sleep(0.5)
            workers = client.scheduler_info()["workers"]
        gpu = next(a for a, w in workers.items() if w.get("resources", {}).get("GPU"))
        logs = {a: root / ("gpu-worker.log" if a == gpu else "cpu-worker.log") for a in workers}
        yield address, logs, gpu
    finally:
        for proc, _ in reversed(procs):
            stop(proc)


# Test files that take longest, longest first (cold studies and runs, clusters, servers; measured on 2
# cores). `make test` hands its two workers whole files in collection order (`--dist loadfile
# --no-loadscope-reorder`); starting with these keeps a long file from starting last while the other
# worker has nothing left to run. The rest follow as collected.
LONGEST_FIRST = (
    "test_study_resume.py",
    "test_ray_runner.py",
    "test_study_flow.py",
    "test_pipeline_flow.py",
    "test_cli.py",
    "test_cluster_runner.py",
    "test_calibrate_flow.py",
    "test_study_rank.py",
    "test_concurrent_runs.py",
    "test_prefect_server.py",
    "test_policy_types_pipeline.py",
    "test_cli_errors.py",
    "test_interrupt.py",
    "test_step_pool.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file's order is kept
