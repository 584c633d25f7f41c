"""Where a flow's steps run: the task runner a command builds from `--runner` and its options.

- `process` (run, study, sweep's default): a pool of `--workers` step processes bound to the CLI
  (capvector.flows.runtime.step_pool.step_runner): steps seed torch's process-global RNG and must not share a
  process.
- `thread` (evaluate, reevaluate's default): Prefect's thread pool, as those flows always ran.
- `dask`: with `--address tcp://host:port`, the steps go to an existing Dask scheduler's workers;
  without, to a cluster made for the run: a LocalCluster of `--workers` single-threaded processes,
  or `--cluster-class` (an importable name) built from `--cluster-kwargs` (JSON).
- `ray`: prefect-ray's RayTaskRunner (capvector.flows.runtime.ray_runner), if installed: with `--address`,
  a cluster's (`host:6379` from a node of it, `ray://host:10001` as a Ray client), else a local Ray.

Every worker of a cluster must import this repository (the `capvector` package) and reach the home
under the same path: steps pass the home and artifact ids, never tensors.

A step may ask the engine for a GPU (`placement`): a training step whose `train.device` starts with
"cuda" is submitted under `dask.annotate(resources={"GPU": 1})` (Ray: `num_gpus=1`), so with Dask it
runs only on a worker started with `--resources GPU=1`. The process and thread pools ignore it.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import sys
from collections.abc import Iterator
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from capvector.flows.runtime.task_runner_fields import DEFAULT_WORKERS, RUNNER_FIELDS

RunnerKind = Literal["process", "thread", "dask", "ray"]
DASK_SCHEMES = ("tcp://", "tls://")
RAY_HINT = "the ray runner needs prefect-ray: pip install prefect-ray"


class RunnerConfig(BaseModel):
    """What `--runner`, `--address`, `--workers`, `--cluster-class` and `--cluster-kwargs` say."""

    model_config = ConfigDict(extra="forbid")
    kind: RunnerKind = Field("process", description=RUNNER_FIELDS["kind"])
    address: str | None = Field(None, description=RUNNER_FIELDS["address"])
    workers: int = Field(DEFAULT_WORKERS, ge=1, description=RUNNER_FIELDS["workers"])
    cluster_class: str | None = Field(None, description=RUNNER_FIELDS["cluster_class"])
    cluster_kwargs: dict[str, Any] = Field(default_factory=dict, description=RUNNER_FIELDS["cluster_kwargs"])

    @field_validator("cluster_class")
    @classmethod
    def _importable(cls, name: str | None) -> str | None:
        if name is None:
            return None
        module, _, attr = name.rpartition(".")
        if not module:
            raise ValueError(f"{name!r} is not a qualified name such as dask_jobqueue.SLURMCluster")
        try:
            obj = getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as exc:
            raise ValueError(f"cannot import {name!r}: {exc}") from None
        if not callable(obj):
            raise ValueError(f"{name!r} is not a class or callable")
        return name

    @model_validator(mode="after")
    def _consistent(self) -> RunnerConfig:
        if self.kind == "ray" and importlib.util.find_spec("prefect_ray") is None:
            raise ValueError(RAY_HINT)
        if self.address is not None:
            self.address = self.address.strip()
            if self.kind not in ("dask", "ray"):
                raise ValueError(f"--address is for --runner dask or ray, not {self.kind}")
            if self.kind == "dask" and not self.address.startswith(DASK_SCHEMES):
                raise ValueError(
                    f"a Dask scheduler address starts with tcp:// or tls:// (got {self.address!r}), "
                    "e.g. tcp://scheduler:8786"
                )
            if not self.address.split("://", 1)[-1]:
                raise ValueError(f"the address {self.address!r} names no host")
        if (self.cluster_class or self.cluster_kwargs) and self.kind != "dask":
            raise ValueError("--cluster-class and --cluster-kwargs are for --runner dask")
        if self.address and (self.cluster_class or self.cluster_kwargs):
            raise ValueError("--address connects to a running scheduler: no --cluster-class/--cluster-kwargs")
        return self


def runner_config(
    kind: str, address: str | None, workers: int, cluster_class: str | None, cluster_kwargs: str | None
) -> RunnerConfig:
    """The CLI's options as a RunnerConfig; `cluster_kwargs` is JSON text (an object)."""
    import json

    kwargs: Any = {}
    if cluster_kwargs:
        try:
            kwargs = json.loads(cluster_kwargs)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--cluster-kwargs is not JSON: {exc}") from None
        if not isinstance(kwargs, dict):
            raise ValueError("--cluster-kwargs must be a JSON object, e.g. '{\"n_workers\": 4}'")
    try:
        return RunnerConfig(
            kind=kind, address=address, workers=workers, cluster_class=cluster_class, cluster_kwargs=kwargs
        )
    except ValidationError as exc:  # one line per problem, named as the option the user typed
        raise ValueError("; ".join(_option_error(e) for e in exc.errors(include_url=False))) from None


def _option_error(error: Any) -> str:
    field = error["loc"][0] if error["loc"] else None
    option = {"kind": "--runner"}.get(field, f"--{field}".replace("_", "-")) if field else None
    text = str(error["msg"]).removeprefix("Value error, ")
    return f"{option}: {text}" if option else text


def build_runner(config: RunnerConfig) -> Any:
    """The Prefect task runner `config` describes (not started: the flow run starts it)."""
    if config.kind == "process":
        from capvector.flows.runtime.step_pool import step_runner

        return step_runner(config.workers)
    if config.kind == "thread":
        from prefect.task_runners import ThreadPoolTaskRunner

        return ThreadPoolTaskRunner(max_workers=config.workers)
    if config.kind == "dask":
        return _dask_runner(config)
    return _ray_runner(config)


def _dask_runner(config: RunnerConfig) -> Any:
    from prefect_dask import DaskTaskRunner  # imports distributed, which sets its loggers' levels

    _quiet_dask_logs()

    if config.address:
        return DaskTaskRunner(address=config.address)
    if config.cluster_class:
        return DaskTaskRunner(cluster_class=config.cluster_class, cluster_kwargs=dict(config.cluster_kwargs))
    local = {
        "n_workers": config.workers,
        "threads_per_worker": 1,  # a step trains with its own threads; two in one process share RNG
        "processes": True,
        "dashboard_address": None,
        "resources": {"GPU": 1},  # a step asking for cuda runs here, and fails as in the process pool
    }
    return DaskTaskRunner(cluster_kwargs={**local, **config.cluster_kwargs})


def _ray_runner(config: RunnerConfig) -> Any:
    try:
        from capvector.flows.runtime.ray_runner import ray_runner
    except ImportError:
        raise ValueError(RAY_HINT) from None
    return ray_runner(config.address, config.workers)


def _quiet_dask_logs() -> None:
    """Dask's own INFO lines (scheduler and worker start/stop, a nanny's closing workers) stay off
    the user's terminal; warnings and errors still show."""
    import logging
    import warnings

    # A local cluster's scheduler serves HTTP (health, metrics) on 8787 or, taken, on another port
    warnings.filterwarnings("ignore", message=r"Port \d+ is already in use", category=UserWarning)
    for name in ("distributed", "distributed.nanny", "distributed.scheduler", "distributed.worker"):
        logger = logging.getLogger(name)
        if logger.getEffectiveLevel() < logging.WARNING:
            logger.setLevel(logging.WARNING)


# ---------------------------------------------------------------------------- step placement
def wants_gpu(config: dict[str, Any]) -> bool:
    """A training step whose config asks for a cuda device."""
    train = config.get("train") if isinstance(config, dict) else None
    return isinstance(train, dict) and str(train.get("device", "")).startswith("cuda")


_checked_for_gpu: set[int] = set()


@contextlib.contextmanager
def placement(config: dict[str, Any]) -> Iterator[None]:
    """Around one step's submission (capvector.flows.runtime.step_submission.StepRunner): ask the current flow
    run's engine for what the step needs. Only a cuda training step on a Dask or Ray runner asks for
    anything."""
    if not wants_gpu(config):
        yield
        return
    runner = _current_runner()
    if _is_instance(runner, "prefect_dask", "DaskTaskRunner"):
        import dask

        _warn_if_no_gpu_worker(runner)
        with dask.annotate(resources={"GPU": 1}):
            yield
    elif _is_instance(runner, "prefect_ray", "RayTaskRunner"):
        from prefect_ray.context import remote_options

        with remote_options(num_gpus=1):
            yield
    else:
        yield


def _current_runner() -> Any:
    from prefect.context import FlowRunContext

    context = FlowRunContext.get()
    return context.task_runner if context is not None else None


def _is_instance(runner: Any, module: str, name: str) -> bool:
    if runner is None or module not in sys.modules:
        return False  # never imports an engine a run does not use
    return isinstance(runner, getattr(sys.modules[module], name))


def _warn_if_no_gpu_worker(runner: Any) -> None:
    """Once per run: say so when no worker of the cluster offers a GPU (its steps would wait)."""
    if id(runner) in _checked_for_gpu:
        return
    _checked_for_gpu.add(id(runner))
    try:
        workers = runner.client.scheduler_info().get("workers", {})
    except Exception:  # cannot ask: the scheduler will say when the step runs
        return
    if not any(w.get("resources", {}).get("GPU", 0) >= 1 for w in workers.values()):
        from capvector.tasks.runtime.progress import emit

        emit(
            "no Dask worker offers a GPU yet: steps asking for cuda wait for one started with "
            "`dask worker <scheduler> --resources GPU=1`"
        )
