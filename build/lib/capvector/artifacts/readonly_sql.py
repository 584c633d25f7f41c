"""The read-only SQL entry point's guards.

Three independent guards, because each alone has a gap:
1. the statement check below (DuckDB's own parser, so comments and string literals cannot fool it):
   exactly one statement, of a reading type. `read_only=True` alone would still let COPY ... TO and
   ATTACH write other files, SET change settings and INSTALL/LOAD pull in extensions;
2. the connection is opened `read_only=True`, so even a statement type the check lets through
   (EXPLAIN ANALYZE of an INSERT, say) cannot change the catalogue file;
3. `enable_external_access=false` with the configuration locked, so no statement can touch other
   files or the network, and a SET inside the query cannot undo that.
One thread: opening a catalogue costs about half as much without a worker pool to start.
(`Catalogue.query` runs the statement on a private snapshot of the file, so a long query holds no
writer off; whatever got through all three would change only that copy.)
These guards are for SQL from outside; the catalogue's own fixed queries (lineage, scores) run on the
file attached read-only to a process-wide database (`catalogue._attached_read`), which is cheaper.
"""

import re

import duckdb

from capvector.artifacts.errors import ReadOnlyViolation

READ_ONLY_CONFIG = {"enable_external_access": False, "lock_configuration": True, "threads": 1}
ALLOWED_TYPES = {
    duckdb.StatementType.SELECT,
    duckdb.StatementType.EXPLAIN,
}  # SELECT covers WITH/SHOW/DESCRIBE
# PRAGMAs that only report; others (`PRAGMA threads=1`, `PRAGMA enable_profiling`) change state.
SHOW_PRAGMAS = {
    "table_info",
    "show_tables",
    "show_tables_expanded",
    "show",
    "database_size",
    "storage_info",
    "version",
    "database_list",
    "functions",
    "collations",
    "platform",
}
PRAGMA_RE = re.compile(r"^\s*pragma\s+([a-z_]+)", re.IGNORECASE)


def check_read_only(sql: str) -> None:
    """Raise ReadOnlyViolation unless `sql` is exactly one reading statement."""
    try:
        statements = duckdb.extract_statements(sql)
    except duckdb.Error as e:
        raise ReadOnlyViolation(f"cannot parse query: {e}") from None
    if len(statements) != 1:
        raise ReadOnlyViolation(f"exactly one statement allowed, got {len(statements)}")
    st = statements[0]
    if st.type in ALLOWED_TYPES:
        return
    if st.type == duckdb.StatementType.PRAGMA:
        m = PRAGMA_RE.match(st.query)
        if m and m.group(1).lower() in SHOW_PRAGMAS:
            return
    raise ReadOnlyViolation(
        f"only reading statements are allowed (SELECT, WITH, SHOW, DESCRIBE, EXPLAIN, "
        f"PRAGMA show_tables/table_info/...); got {st.type.name}"
    )
