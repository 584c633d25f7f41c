"""What each `capvector.flows.runtime.task_runners.RunnerConfig` field means, declared once: the model's field
descriptions and the CLI's `--runner`, `--address`, `--workers`, `--cluster-class`, `--cluster-kwargs` help
(capvector.flows.cli.runner_options). No imports: the config model and the CLI both read it."""

DEFAULT_WORKERS = 2
RUNNER_FIELDS = {
    "kind": "process (a pool of --workers, default) | dask | ray; evaluate, reevaluate: thread (default)",
    "address": "dask: tcp://host:port of a running scheduler; ray: its address",
    "workers": "worker processes of a pool or a local cluster",
    "cluster_class": "dask: a cluster class to start, e.g. dask_jobqueue.SLURMCluster",
    "cluster_kwargs": "dask: that cluster's keyword arguments, JSON",
}
