"""Where things live: CAPVECTOR_HOME holds the store (any fsspec URL) and, when local, the catalogue."""

import hashlib
import os
import posixpath
from pathlib import Path

import fsspec
from fsspec.implementations.local import LocalFileSystem
from fsspec.spec import AbstractFileSystem


def default_home() -> str:
    """CAPVECTOR_HOME, else ./capvector_home (git-ignored)."""
    return os.environ.get("CAPVECTOR_HOME", "capvector_home")


def is_local(url: str) -> bool:
    return isinstance(fsspec.core.url_to_fs(url)[0], LocalFileSystem)


def filesystem(url: str) -> tuple[AbstractFileSystem, str]:
    """The fsspec filesystem of `url` and the path on it; a remote one without a listing cache.

    Other processes and machines commit to a shared store: s3fs (gcsfs, adlfs alike) caches every
    listing it makes and never refreshes it, and answers `exists`/`info` from a cached listing of the
    parent, so an artifact another process committed after this one listed its shard stayed
    invisible (`no artifact …` for one that was in the bucket). Every check asks the server instead.
    A local filesystem keeps no listings: it is returned as it is."""
    fs, path = fsspec.core.url_to_fs(url)
    if isinstance(fs, LocalFileSystem):
        return fs, path
    try:
        return fsspec.core.url_to_fs(url, use_listings_cache=False)
    except TypeError:  # a filesystem without that option (fsspec's own all take it): as it is
        return fs, path


def make_folder(fs: AbstractFileSystem, path: str) -> None:
    """A folder, on a local filesystem. An object store has no folders (a key needs no parent), and
    s3fs's makedirs there costs a request (it looks the bucket up): nothing is done."""
    if isinstance(fs, LocalFileSystem):
        fs.makedirs(path, exist_ok=True)


def store_url(home: str) -> str:
    return posixpath.join(str(home), "store")


def local_cache_dir(home: str) -> Path:
    """Local directory for remote-store downloads and a remote home's catalogue.

    DuckDB needs a local file, and remote objects must be materialised before a trainer can mmap
    them; CAPVECTOR_CACHE overrides the per-home default under ~/.cache/capvector.
    """
    base = Path(os.environ.get("CAPVECTOR_CACHE", Path.home() / ".cache" / "capvector"))
    return base / hashlib.sha256(str(home).encode()).hexdigest()[:16]


def catalogue_path(home: str) -> Path:
    """<home>/catalogue.duckdb for a local home; the local cache for a remote one (it can be rebuilt)."""
    if is_local(str(home)):
        return Path(fsspec.core.url_to_fs(str(home))[1]) / "catalogue.duckdb"
    return local_cache_dir(home) / "catalogue.duckdb"
