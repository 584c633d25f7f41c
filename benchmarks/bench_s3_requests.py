"""Requests a cold `capvector run --preset smoke` (or `capvector study --preset study-smoke`) makes to an
S3 home, by kind, for this code and for an earlier revision in the same session.

Run: .venv/bin/python benchmarks/bench_s3_requests.py [--preset study-smoke] [--before REV]
Writes benchmarks/results/s3_requests.{md,json} (smoke) or s3_requests_<preset>.{md,json}.

The home is a bucket on a local moto server, whose request log is counted (method, and the query
parameters that tell a listing from a read). On loopback a request costs moto ~5 ms of CPU; a real
object store answers in ~30 ms (issue 23), so every request saved is latency a remote run no longer
waits for. Counts do not depend on the machine's speed or load, unlike times: the figure to compare.
With `--before REV` the same cold run is made with the code of REV (a temporary git worktree).
"""

import argparse
import collections
import json
import logging
import os
import platform
import re
import resource
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"
REQUEST = re.compile(r'"(GET|HEAD|PUT|POST|DELETE) (\S+) HTTP')


class _Requests(logging.Handler):
    """Counts moto's request log lines (werkzeug's) by kind."""

    def __init__(self) -> None:
        super().__init__()
        self.kinds: collections.Counter[str] = collections.Counter()

    def emit(self, record: logging.LogRecord) -> None:
        m = REQUEST.search(record.getMessage())
        if m:
            self.kinds[_kind(m.group(1), m.group(2))] += 1


def _kind(method: str, path: str) -> str:
    if "list-type" in path:
        return "LIST"
    if method == "POST" and "delete" in path:
        return "DELETE (batch)"
    bucket_only = path.strip("/").count("/") == 0 and "?" not in path
    return f"{method} bucket" if bucket_only else f"{method} object"


def command_of(preset: str) -> str:
    """`study` for a study preset, `run` for a recipe's."""
    return "study" if preset.startswith("study-") else "run"


def cold_run(cwd: Path, env: dict[str, str], counter: _Requests, preset: str) -> dict:
    """One cold run of `preset` on a fresh bucket: its requests by kind, wall and CPU seconds."""
    import boto3

    bucket = f"bench-{uuid.uuid4().hex[:10]}"
    boto3.client("s3").create_bucket(Bucket=bucket)
    counter.kinds.clear()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "capvector",
            "--home",
            f"s3://{bucket}/home",
            command_of(preset),
            "--preset",
            preset,
        ],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.exit(f"the {preset} run failed:\n{proc.stderr[-3000:]}")
    kinds = dict(counter.kinds.most_common())
    return {
        "requests": sum(kinds.values()),
        "by_kind": kinds,
        "wall_s": round(wall, 1),
        "run_cpu_s": round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="smoke", help="smoke (a recipe run) or study-smoke (a study)")
    ap.add_argument("--before", default=None, help="also count the requests of this revision (a worktree)")
    args = ap.parse_args()
    stem = "s3_requests" if args.preset == "smoke" else f"s3_requests_{args.preset.replace('-', '_')}"

    from moto_s3 import moto_s3

    counter = _Requests()
    werkzeug = logging.getLogger("werkzeug")
    werkzeug.setLevel(logging.INFO)
    werkzeug.addHandler(counter)
    werkzeug.propagate = False
    work = Path(tempfile.mkdtemp(prefix="s3-requests-"))

    def env(name: str, **extra: str) -> dict[str, str]:
        return {
            **os.environ,  # moto's address and keys among them
            "CAPVECTOR_CACHE": str(work / name / "cache"),
            "PREFECT_HOME": str(work / name / "prefect"),
            "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
            "CAPVECTOR_QUIET": "1",
            **extra,
        }

    result = {"machine": f"{platform.machine()}, {os.cpu_count()} cores", "preset": args.preset, "after": {}}
    with moto_s3():
        result["after"] = cold_run(REPO, env("after"), counter, args.preset)
        if args.before:
            tree = work / "before-tree"
            rev = ["git", "rev-parse", "--short", args.before]  # a name like HEAD, recorded as its commit
            named = subprocess.run(rev, cwd=REPO, capture_output=True, text=True, check=True)
            args.before = named.stdout.strip()
            add = ["git", "worktree", "add", "--detach", "-f", str(tree), args.before]
            subprocess.run(add, cwd=REPO, check=True)
            try:
                result["before"] = cold_run(tree, env("before", PYTHONPATH=str(tree)), counter, args.preset)
                result["before"]["revision"] = args.before
            finally:
                subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO, check=False)
            result["ratio"] = round(result["after"]["requests"] / result["before"]["requests"], 2)
    print(json.dumps(result, indent=1))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=1) + "\n")
    (RESULTS / f"{stem}.md").write_text(_markdown(result))


def _markdown(result: dict) -> str:
    after, before = result["after"], result.get("before")
    kinds = sorted(set(after["by_kind"]) | set((before or {}).get("by_kind", {})))
    head = "| request | " + (f"before ({before['revision']}) | " if before else "") + "after |\n"
    rule = "|---|" + ("---:|" if before else "") + "---:|\n"
    rows = "".join(
        f"| {k} | "
        + (f"{before['by_kind'].get(k, 0)} | " if before else "")
        + f"{after['by_kind'].get(k, 0)} |\n"
        for k in kinds
    )
    was = f"**{before['requests']}** | " if before else ""
    total = f"| **all** | {was}**{after['requests']}** |\n"
    ratio = f"\nAfter / before: **{result['ratio']}×** the requests.\n" if before else ""
    preset = result["preset"]
    flags = ("" if preset == "smoke" else f" --preset {preset}") + (
        f" --before {before['revision']}" if before else ""
    )
    return (
        f"# Requests of a cold {preset} run to an S3 home\n\n"
        f"`benchmarks/bench_s3_requests.py{flags}` on "
        f"{result['machine']}: `capvector {command_of(preset)} --preset {preset}` on a fresh bucket of a "
        "local moto server, "
        "its request log counted. Counts are the figure to compare (times depend on load); a real object "
        "store takes ~30 ms a request.\n\n"
        + head
        + rule
        + rows
        + total
        + ratio
        + "\nCPU of the run's processes (moto's own not included): "
        + (f"{before['run_cpu_s']} s before, " if before else "")
        + f"{after['run_cpu_s']} s after; wall {after['wall_s']} s"
        + (f" (before {before['wall_s']} s)" if before else "")
        + ", both under whatever else ran.\n"
    )


if __name__ == "__main__":
    main()
