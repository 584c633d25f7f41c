"""Catalogue schema as forward migrations: the version table records which have been applied."""

from __future__ import annotations

from collections.abc import Sequence

import duckdb

from capvector.artifacts.errors import SchemaTooNew

V1 = """
CREATE TABLE artifacts (
    id VARCHAR PRIMARY KEY, kind VARCHAR NOT NULL, name VARCHAR NOT NULL, layout VARCHAR NOT NULL,
    size_bytes BIGINT NOT NULL, n_files INTEGER NOT NULL, config JSON, code_version VARCHAR,
    library_versions JSON, created_at TIMESTAMP, flow_run_id VARCHAR, task_run_id VARCHAR
);
CREATE TABLE edges (
    parent VARCHAR NOT NULL, child VARCHAR NOT NULL, role VARCHAR NOT NULL, attrs JSON,
    PRIMARY KEY (parent, child, role)
);
CREATE INDEX edges_child ON edges (child);
CREATE INDEX edges_parent ON edges (parent);
CREATE TABLE vector_stats (
    stats_id VARCHAR NOT NULL, vector_id VARCHAR NOT NULL, tensor VARCHAR NOT NULL, "group" VARCHAR,
    numel BIGINT, l2 DOUBLE, rel_norm DOUBLE, cosine_ref DOUBLE, sign_agreement DOUBLE, extras JSON,
    PRIMARY KEY (stats_id, tensor)
);
CREATE TABLE eval_episodes (
    evaluation_id VARCHAR NOT NULL, episode INTEGER NOT NULL, checkpoint_id VARCHAR NOT NULL,
    task VARCHAR NOT NULL, seed BIGINT NOT NULL, success BOOLEAN NOT NULL, steps INTEGER NOT NULL,
    "return" DOUBLE NOT NULL, fingerprint VARCHAR NOT NULL, library_versions JSON,
    evaluated_at TIMESTAMP NOT NULL, extras JSON,
    PRIMARY KEY (evaluation_id, episode)
);
CREATE TABLE eval_tasks (
    evaluation_id VARCHAR NOT NULL, task VARCHAR NOT NULL, checkpoint_id VARCHAR NOT NULL,
    fingerprint VARCHAR NOT NULL, n_episodes INTEGER NOT NULL, success_rate DOUBLE NOT NULL,
    mean_return DOUBLE NOT NULL, mean_steps DOUBLE NOT NULL, library_versions JSON,
    evaluated_at TIMESTAMP NOT NULL,
    PRIMARY KEY (evaluation_id, task)
);
CREATE INDEX eval_tasks_checkpoint ON eval_tasks (checkpoint_id);
CREATE TABLE runs (
    flow_run_id VARCHAR PRIMARY KEY, flow_name VARCHAR NOT NULL, parameters JSON, state VARCHAR,
    started_at TIMESTAMP, ended_at TIMESTAMP
);
"""

# Which state of the store the catalogue last caught up with (see catalogue.store_fingerprint): one row
# per store; `fingerprint` is NULL when the listing could not be trusted (remote stores: only the time).
V2 = """
CREATE TABLE store_sync (store VARCHAR PRIMARY KEY, fingerprint VARCHAR, synced_at TIMESTAMP NOT NULL);
"""

# Whether the sidecar indexed was sealed: an unsealed sidecar must never replace, in `show`, a read or a
# rebuild, a record the catalogue saw sealed (someone stripped the seal and wrote `format: 1` to edit it).
# NULL for rows indexed before this column existed (not known).
V3 = """
ALTER TABLE artifacts ADD COLUMN sealed BOOLEAN;
"""

# One row per 2-D tensor of a `vector_spectrum` artifact (`capvector vector spectrum`): its ranks at 50 / 90
# / 99 % of the energy and its largest singular value; the singular values themselves stay in the artifact.
V4 = """
CREATE TABLE vector_spectrum (
    spectrum_id VARCHAR NOT NULL, vector_id VARCHAR NOT NULL, subtrahend_id VARCHAR,
    tensor VARCHAR NOT NULL, module_kind VARCHAR NOT NULL, rows BIGINT NOT NULL, cols BIGINT NOT NULL,
    full_rank BIGINT NOT NULL, rank50 BIGINT NOT NULL, rank90 BIGINT NOT NULL, rank99 BIGINT NOT NULL,
    top_singular_value DOUBLE NOT NULL,
    PRIMARY KEY (spectrum_id, tensor)
);
"""

SCHEMA_VERSION_DDL = (
    "CREATE TABLE IF NOT EXISTS schema_version (version INTEGER PRIMARY KEY, applied_at TIMESTAMP)"
)

# Append (version, sql) pairs; never edit an applied one. Versions must increase by one.
MIGRATIONS: list[tuple[int, str]] = [(1, V1), (2, V2), (3, V3), (4, V4)]

DATA_TABLES = ("artifacts", "edges", "vector_stats", "vector_spectrum", "eval_episodes", "eval_tasks", "runs")
# Rows derived from one artifact, by the column naming it: what `gc` removes for an artifact that is gone.
ARTIFACT_COLUMNS = {
    "artifacts": "id",
    "edges": "child",
    "vector_stats": "stats_id",
    "vector_spectrum": "spectrum_id",
    "eval_episodes": "evaluation_id",
    "eval_tasks": "evaluation_id",
}


def current_version(con: duckdb.DuckDBPyConnection) -> int:
    """Applied schema version; 0 for an empty database.

    Asked directly rather than through information_schema, whose first use on a fresh connection
    costs more than the rest of opening the catalogue."""
    try:
        return con.execute("SELECT coalesce(max(version), 0) FROM schema_version").fetchone()[0]
    except duckdb.CatalogException:
        return 0


def check_version(con: duckdb.DuckDBPyConnection, path: str, migrations: Sequence[tuple[int, str]]) -> int:
    """Applied version, refusing a catalogue written by newer code (SchemaTooNew names both versions)."""
    found, known = current_version(con), migrations[-1][0]
    if found > known:
        raise SchemaTooNew(found, known, path)
    return found


def migrate(
    con: duckdb.DuckDBPyConnection, path: str, migrations: Sequence[tuple[int, str]] = MIGRATIONS
) -> int:
    """Apply the missing migrations in one transaction each; returns the version reached."""
    found = check_version(con, path, migrations)
    for version, sql in migrations:
        if version <= found:
            continue
        con.execute("BEGIN")
        try:
            con.execute(SCHEMA_VERSION_DDL)
            con.execute(sql)
            con.execute("INSERT INTO schema_version VALUES (?, now()::TIMESTAMP)", [version])
            con.execute("COMMIT")
        except BaseException:
            con.execute("ROLLBACK")
            raise
        found = version
    return found
