"""A new machine catching up with a remote home: one sidecar read at a time against SIDECAR_READERS
in parallel, and an open after nothing changed (the change token).

Run: .venv/bin/python benchmarks/bench_remote_catch_up.py [--artifacts 600] [--latency-ms 30]
Writes benchmarks/results/remote_catch_up.{md,json}.

The home is an S3 bucket on a local moto server (loopback: a round trip takes well under 1 ms, where a
real object store takes ~30 ms, measured on main in issue 23). `--latency-ms` adds that delay to every
object read of the store (`ArtifactStore`'s filesystem `cat_file`), so the figures show what the
network would cost; 0 measures loopback alone. Each arm opens a fresh catalogue (its own
CAPVECTOR_CACHE) of the same store, alternating, median of --rounds.
"""

import argparse
import contextlib
import json
import logging
import os
import platform
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
RESULTS = HERE / "results"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--artifacts", type=int, default=600)
    ap.add_argument("--latency-ms", type=float, default=30.0)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()

    import boto3
    from moto_s3 import moto_s3

    from capvector.artifacts import catalogue as catalogue_mod
    from capvector.artifacts.api import ArtifactsAPI

    logging.getLogger("werkzeug").setLevel(logging.WARNING)
    s3 = contextlib.ExitStack()
    s3.enter_context(moto_s3())
    bucket = f"bench-{uuid.uuid4().hex[:8]}"
    boto3.client("s3").create_bucket(Bucket=bucket)
    home = f"s3://{bucket}/home"
    work = Path(tempfile.mkdtemp(prefix="catch-up-"))

    os.environ["CAPVECTOR_CACHE"] = str(work / "writer")
    writer = ArtifactsAPI(home)
    t0 = time.perf_counter()
    root = writer.register_json({"root": 1}, "dataset", "demos").id
    for i in range(args.artifacts - 1):
        writer.register_json({"i": i}, "metrics", f"eval {i}", parents=[(root, "data")])
    register_s = time.perf_counter() - t0

    delay = args.latency_ms / 1000
    fs = writer.store.fs  # fsspec caches filesystem instances: every reader below gets this one
    real_cat_file = fs.cat_file  # an async filesystem's sync methods are set on the instance
    reads = []

    def slow_cat_file(path, *a, **k):
        reads.append(path)
        time.sleep(delay)
        return real_cat_file(path, *a, **k)

    fs.cat_file = slow_cat_file

    def open_fresh(readers: int) -> float:
        catalogue_mod.SIDECAR_READERS = readers
        os.environ["CAPVECTOR_CACHE"] = str(work / f"reader-{uuid.uuid4().hex[:8]}")
        t = time.perf_counter()
        api = ArtifactsAPI(home)
        seconds = time.perf_counter() - t
        n = int(api.query("SELECT count(*) AS n FROM artifacts")["n"][0])
        assert n == args.artifacts, f"indexed {n} of {args.artifacts}"
        assert api.store.fs is fs and len(reads) >= args.artifacts, "the added latency was not applied"
        reads.clear()
        return seconds

    sequential, parallel = [], []
    for _ in range(args.rounds):
        sequential.append(open_fresh(1))
        parallel.append(open_fresh(catalogue_mod.SIDECAR_READERS_DEFAULT))

    # an open after nothing changed: the token read alone, against the listing that was done before
    catalogue_mod.SIDECAR_READERS = catalogue_mod.SIDECAR_READERS_DEFAULT
    os.environ["CAPVECTOR_CACHE"] = str(work / "steady")
    ArtifactsAPI(home)
    unchanged = []
    for _ in range(args.rounds):
        t = time.perf_counter()
        ArtifactsAPI(home)
        unchanged.append(time.perf_counter() - t)
    fs.cat_file = real_cat_file
    s3.close()

    med = statistics.median
    result = {
        "artifacts": args.artifacts,
        "latency_ms": args.latency_ms,
        "rounds": args.rounds,
        "readers": catalogue_mod.SIDECAR_READERS_DEFAULT,
        "register_s": round(register_s, 2),
        "catch_up_sequential_s": round(med(sequential), 3),
        "catch_up_parallel_s": round(med(parallel), 3),
        "speedup": round(med(sequential) / med(parallel), 2),
        "open_unchanged_s": round(med(unchanged), 4),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
    }
    print(json.dumps(result, indent=1))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "remote_catch_up.json").write_text(json.dumps(result, indent=1) + "\n")
    (RESULTS / "remote_catch_up.md").write_text(
        "# A new machine catching up with a remote home (issue 23)\n\n"
        f"`benchmarks/bench_remote_catch_up.py --artifacts {args.artifacts} --latency-ms {args.latency_ms:g}`"
        f" on {result['machine']}: an S3 home on a local moto server, {args.latency_ms:g} ms added to every"
        f" object read (a real object store's round trip); medians of {args.rounds} fresh opens.\n\n"
        "| what | seconds |\n|---|---|\n"
        f"| fresh catalogue, sidecars read one at a time (before) | {result['catch_up_sequential_s']} |\n"
        f"| fresh catalogue, {result['readers']} sidecar reads in parallel "
        f"| {result['catch_up_parallel_s']} |\n"
        f"| **speed-up** | **{result['speedup']}×** |\n"
        f"| open after nothing changed (reads the change token, lists nothing) "
        f"| {result['open_unchanged_s']} |\n\n"
        "Before the change token, a remote home was listed at most every 60 s, so a driver that had "
        "opened its catalogue less than a minute before a worker's commits answered `0 rows` for them; "
        "now each open reads the token (one small object) and lists only when it changed.\n"
    )


if __name__ == "__main__":
    main()
