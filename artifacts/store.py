"""Content-addressed artifact store on a local directory or any fsspec filesystem.

Layout under the root:
    objects/<id[:2]>/<id>/<files...>   the content (one file, or a directory tree)
    objects/<id[:2]>/<id>.json         the sidecar (ArtifactRecord); written last = the commit point
    tmp/<uuid>/                        staging; a killed writer leaves garbage only here
    runs/<flow_run_id>.json            flow-run records, so the catalogue can be rebuilt from the store
    index/<key[:2]>/<key>.json         a remote home's content-cache index: step cache key -> artifact id
                                       (capvector.tasks.runtime.caching), one object per key, so any
                                       machine answers a cached step with one GET instead of a listing
    quarantine/<time>/<id>/            objects without a sidecar that `gc` moved aside (never deleted)
    changes                            remote stores: a token rewritten after every sidecar or run record
                                       (a catalogue reads it, one small GET, to know whether to list)

An artifact is visible only once its sidecar exists; an object directory without one is invisible.
Locally an object directory is committed by one rename. An object store (S3, GCS, ...) has no
directories to rename: each staged file is copied to its final key (one atomic copy per object, server
side), then the sidecar is written; a writer killed before its sidecar leaves only invisible keys.
`gc` never deletes one: a write killed before its sidecar and an artifact whose sidecar was lost look
alike, so it is moved to quarantine/ (or, when something names it as a parent, left in place).
Ids: sha256 of the file bytes (so `sha256sum` agrees) or, for a directory, of its
canonical manifest (see hashing.manifest_bytes).

Integrity: nothing wrong is ever served under a trusted id.
- Content: `path()` re-hashes every file of the artifact by default (size and mtime prove nothing:
  bit rot, `cp -a`, rsync and restores keep them). Within one process a file this process hashed is
  not hashed again while its inode, size, mtime and ctime are unchanged, for at most
  VERIFIED_TTL_NS, and only once its times are RACY_WINDOW_NS old (a coarse clock could otherwise
  give a change the same times); across processes every read re-hashes.
- Streaming: a computation may read an artifact's own files (`stream_path`) and hash them as it reads,
  then hand those hashes to `check_read` before it registers anything: the hash taken while reading
  is the check, so the bytes are read once, not once to verify and once to compute.
- Parents: a registration re-checks each parent (sealed sidecar, content hash) before writing; a
  parent whose every file the caller hashed while reading it (`parent_hashes`) is not hashed again.
- Staging: content written or copied into `staging()` (the store's own `tmp/`) is committed by a
  rename, with the hashes its writer took, not copied and hashed once more.
- Metadata: the sidecar carries a seal, sha256 of its canonical metadata (records.metadata_digest);
  an edited sidecar is refused naming the id. Format-1 sidecars (written before sealing) still load,
  as unsealed, unless `unsealed_guard` (set by capvector.artifacts.api) knows the artifact was registered
  sealed: a stripped seal is then refused like a broken one. The seal catches accidental edits and
  tooling bugs, not a writer who recomputes it.
- `audit()` is the full check behind `capvector verify`: no memo, no writes.
"""

import contextlib
import errno
import fcntl
import io
import json
import os
import posixpath
import re
import shutil
import stat
import threading
import time
import unicodedata
import uuid
from collections.abc import Callable, Iterable, Iterator, Mapping
from datetime import datetime
from pathlib import Path
from typing import Any, BinaryIO

from fsspec.implementations.local import LocalFileSystem
from pydantic import BaseModel

from capvector.artifacts import home as home_mod
from capvector.artifacts.errors import (
    AmbiguousId,
    ArtifactNotFound,
    CorruptArtifact,
    MalformedId,
    PathEscape,
    UnknownParent,
)
from capvector.artifacts.hashing import copy_and_hash, hash_file, hash_stream, manifest_id
from capvector.artifacts.provenance import code_version
from capvector.artifacts.records import (
    ArtifactMeta,
    ArtifactRecord,
    FileEntry,
    IntegrityVerdict,
    ParentHashes,
    ParentLike,
    ParentRef,
    RunRecord,
    SealBroken,
    parse_sidecar,
    safe_relpath,
    seal_sidecar,
)
from capvector.durable import fsync_dir, write_atomic

PREFIX_RE = re.compile(r"^[0-9a-f]{6,64}$")
RUN_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
CHANGES = "changes"  # a remote store's change token (ArtifactStore._note_change)
INDEX = "index"  # content-cache index objects (ArtifactStore.put_index_entry)
KEY_RE = re.compile(r"^[0-9a-f]{64}$")
# An index entry is a few hundred bytes: anything much larger is not one, and is not read into memory.
INDEX_ENTRY_MAX = 4096
FICLONE = 0x40049409  # linux/fs.h: share the source's blocks (btrfs, XFS, bcachefs); copy-on-write


# In-process memo of verified local files: stat key -> (sha256, when it was hashed, time_ns).
VERIFIED_TTL_NS = 300 * 10**9
RACY_WINDOW_NS = 2 * 10**9
_MEMO_MAX = 100_000
_verified: dict[tuple[Any, ...], tuple[str, int]] = {}
_verified_lock = threading.Lock()


def _valid_id(id_or_prefix: object) -> str:
    """An artifact id or prefix, lowercased; MalformedId for anything else."""
    if not isinstance(id_or_prefix, str) or not PREFIX_RE.match(id_or_prefix.lower()):
        raise MalformedId(f"{id_or_prefix!r} is not an artifact id (6 to 64 hex characters)")
    return id_or_prefix.lower()


def clear_verified_memo() -> None:
    """Forget which files this process verified (the next read of each re-hashes it)."""
    with _verified_lock:
        _verified.clear()


def _stat_key(path: str, st: os.stat_result) -> tuple[Any, ...]:
    # ctime cannot be set from user space: any write, utime, chmod or rename moves it.
    return (path, st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def _hash_local(path: str, expected: str, memo: bool = True) -> tuple[str, int]:
    """(sha256, size) of a local file, read in full unless this process already hashed this very
    file to `expected` (same inode, size, mtime and ctime) less than VERIFIED_TTL_NS ago.

    Only a file whose times were over RACY_WINDOW_NS old when the read began is remembered: file
    times come from a coarse clock, so a write just after a fresh change could leave them as they were.
    """
    st = os.stat(path)
    key, now = _stat_key(path, st), time.time_ns()
    if memo:
        with _verified_lock:
            hit = _verified.get(key)
        if hit is not None and hit[0] == expected and now - hit[1] < VERIFIED_TTL_NS:
            return expected, st.st_size
    with open(path, "rb", buffering=0) as f:
        digest, size = hash_stream(f)
        after = os.fstat(f.fileno())
    settled = now - max(after.st_mtime_ns, after.st_ctime_ns) > RACY_WINDOW_NS
    if memo and digest == expected and settled and _stat_key(path, after) == key:
        with _verified_lock:
            if len(_verified) >= _MEMO_MAX:
                _verified.clear()
            _verified[key] = (digest, now)
    return digest, size


def copy_file(src: str | os.PathLike[str] | BinaryIO, dst: str | os.PathLike[str]) -> None:
    """Copy a file (a path, or a file open for reading) to a new path by the kernel's fastest way: a
    reflink where the filesystem has them (no bytes copied), else copy_file_range (no pass through
    user space), else a plain copy.

    Never a hard link: a later edit of either file would change the other."""
    with contextlib.ExitStack() as stack:
        fi = src if hasattr(src, "fileno") else stack.enter_context(open(src, "rb"))  # type: ignore[arg-type]
        fo = stack.enter_context(open(dst, "xb"))
        with contextlib.suppress(OSError):
            fcntl.ioctl(fo.fileno(), FICLONE, fi.fileno())
            return
        offset = 0
        try:
            while n := os.copy_file_range(fi.fileno(), fo.fileno(), 1 << 30, offset):
                offset += n
        except OSError:  # no copy_file_range here (old kernel, some filesystems): start over in user space
            fi.seek(0)
            fo.seek(0)
            fo.truncate()
            shutil.copyfileobj(fi, fo, 1 << 20)


def copy_in(src: str | os.PathLike[str], dst: str | os.PathLike[str], skip: Iterable[str] = ()) -> None:
    """Copy a local file or directory tree (every file, as `put_dir` stores it; members in `skip` are
    left for the caller to write) to a new path, by `copy_file`, and start writing the copies back to
    disk. Meant for `ArtifactStore.staging()`: a private copy cannot change under its reader."""
    src, dst, skip = os.path.abspath(os.fspath(src)), Path(dst), set(skip)
    if not os.path.isdir(src):
        copy_file(src, dst)
        flush_soon(dst)
        return
    dst.mkdir()
    for rel, full in _members(src):
        if rel not in skip:
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            copy_file(full, dst / rel)
            flush_soon(dst / rel)


def fsync_file(path: str | os.PathLike[str]) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def flush_soon(path: str | os.PathLike[str]) -> None:
    """Write a fresh file back to disk in a helper thread while other work goes on, so that the fsync
    before its commit finds little left to do."""

    def flush() -> None:
        with contextlib.suppress(OSError):  # discarded meanwhile (a failed command): nothing to keep
            fsync_file(path)

    threading.Thread(target=flush, daemon=True).start()


def _members(src_dir: str) -> list[tuple[str, str]]:
    """(relative path, full path) of every file under a directory, each a regular file inside it.

    Refused, naming the member (ValueError): a symlinked directory (following it could loop or pull in
    an unbounded tree), a symlink whose target lies outside the folder or is not a regular file
    (`notes.txt -> /etc/passwd`), and anything that is not a regular file: a FIFO would hang the
    reader, a device (`/dev/zero`) would be copied until the disk fills. A link to a regular file
    inside the folder is stored as its content."""
    members = []
    root = os.path.realpath(src_dir)
    for dirpath, dirnames, filenames in os.walk(src_dir):
        for d in dirnames:
            if os.path.islink(os.path.join(dirpath, d)):
                raise ValueError(f"symlinked directory {os.path.join(dirpath, d)} cannot be stored")
        for fn in filenames:
            full = os.path.join(dirpath, fn)
            rel = safe_relpath(os.path.relpath(full, src_dir).replace(os.sep, "/"))
            _regular_member(full, rel, src_dir, root)
            members.append((rel, full))
    return sorted(members)


def _what(mode: int) -> str:
    for test, name in [
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISDIR, "a directory"),
    ]:
        if test(mode):
            return name
    return "not a regular file"


def _regular_member(full: str, rel: str, src_dir: str, root: str) -> int:
    """Size of a member that is a regular file inside the folder (directly or by a link that stays
    inside); ValueError naming it otherwise. Nothing is opened: a FIFO is never waited on."""
    st = os.lstat(full)
    if stat.S_ISLNK(st.st_mode):
        target = os.path.realpath(full)
        if not (target + os.sep).startswith(root + os.sep) or target == root:
            raise ValueError(
                f"{rel} in {src_dir} is a symlink to {target}, outside the folder; only regular files "
                "inside the folder are stored"
            )
        st = os.stat(target)
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(
                f"{rel} in {src_dir} is a symlink to {_what(st.st_mode)}; only regular files are stored"
            )
    elif not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{rel} in {src_dir} is {_what(st.st_mode)}; only regular files are stored")
    return st.st_size


class _Bounded(io.RawIOBase):
    """At most `limit` bytes of `f`: a member is read up to the size it was listed with, plus one byte
    to notice that it grew (a file that grows without end must not fill the disk)."""

    def __init__(self, f: BinaryIO, limit: int):
        self.f, self.left = f, limit

    def readable(self) -> bool:
        return True

    def readinto(self, buf: Any) -> int:
        if self.left <= 0:
            return 0
        view = memoryview(buf)[: self.left]
        n = self.f.readinto(view) or 0
        self.left -= n
        return n


def _open_member(full: str, rel: str, src_dir: str) -> tuple[BinaryIO, int]:
    """A member of a folder being stored, opened only if it is (still) a regular file inside the
    folder (checked again on the open file: it may have been swapped since it was listed), and its size."""
    size = _regular_member(full, rel, src_dir, os.path.realpath(src_dir))
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
    if not os.path.islink(full):
        flags |= getattr(os, "O_NOFOLLOW", 0)
    fd = os.open(full, flags)
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode) or st.st_size != size:
        os.close(fd)
        raise ValueError(f"{rel} in {src_dir} changed while it was being stored; run the command again")
    return os.fdopen(fd, "rb", buffering=0), size


# Characters a one-line name must not hold: control characters (newline, tab, escape), the Unicode line
# and paragraph separators, and format characters (bidi overrides that reorder what a terminal shows).
_NOT_IN_A_LINE = ("Cc", "Cf", "Zl", "Zp")


def check_single_line(what: str, value: str) -> str:
    """Refuse a name, kind or role that is not one printable line: a newline in a name would draw a
    forged lineage line in every view. Raises ValueError naming the field and the character."""
    if not isinstance(value, str) or not value:
        raise ValueError(f"artifact {what} must be a non-empty string, got {value!r}")
    for i, c in enumerate(value):
        if unicodedata.category(c) in _NOT_IN_A_LINE:
            raise ValueError(
                f"artifact {what} {value!r} holds the control character U+{ord(c):04X} at position {i}; "
                "names are single printable lines"
            )
    return value


def _check_labels(kind: str, name: str) -> None:
    check_single_line("kind", kind)
    check_single_line("name", name)


def _plain_name(filename: str) -> str:
    filename = safe_relpath(filename)
    if "/" in filename:
        raise PathEscape(f"filename {filename!r} must be a plain name")
    return filename


def _expect(hashes: Mapping[str, str], entries: list[tuple[str, int, str]]) -> None:
    """Bytes copied in must be those the caller hashed: a file that changed since is refused."""
    for rel, _, digest in entries:
        if hashes.get(rel, digest) != digest:
            raise ValueError(
                f"{rel} changed since it was hashed (sha256 {digest[:12]}…, not {hashes[rel][:12]}…)"
            )


class GcResult(BaseModel):
    """What the store's gc did: staging leftovers removed; objects without a sidecar moved aside
    (their new paths) or, being named as a parent, kept in place (their ids)."""

    removed: list[str] = []
    quarantined: list[str] = []
    kept: list[str] = []


class ArtifactStore:
    """Write-once, verify-on-read storage of files and directories named by their sha256, with
    sealed metadata."""

    def __init__(
        self, root: str | os.PathLike[str] | None = None, cache_dir: str | os.PathLike[str] | None = None
    ):
        self.url = str(root) if root is not None else home_mod.store_url(home_mod.default_home())
        self.fs, root_path = home_mod.filesystem(self.url)
        self.local = isinstance(self.fs, LocalFileSystem)
        self.root = os.path.abspath(root_path) if self.local else root_path.rstrip("/")
        self.cache_dir = Path(cache_dir) if cache_dir else home_mod.local_cache_dir(self.url) / "objects"
        home_mod.make_folder(self.fs, self._p("objects"))
        # Called with every record read from an unsealed sidecar (see capvector.artifacts.api: it raises
        # CorruptArtifact when the catalogue recorded that artifact sealed, i.e. the seal was stripped).
        self.unsealed_guard: Callable[[ArtifactRecord], None] | None = None

    # ---------------------------------------------------------------- paths
    def _p(self, *parts: str) -> str:
        return posixpath.join(self.root, *parts)

    def object_path(self, artifact_id: str) -> str:
        return self._p("objects", artifact_id[:2], artifact_id)

    def sidecar_path(self, artifact_id: str) -> str:
        return self._p("objects", artifact_id[:2], artifact_id + ".json")

    # ---------------------------------------------------------------- low-level writes
    def _write_stream(self, src: BinaryIO, dst: str) -> tuple[str, int]:
        """Copy + hash in one pass; fsync locally so the later rename never exposes a partial file."""
        if self.local:
            with open(dst, "wb") as out:
                digest = copy_and_hash(src, out)
                out.flush()
                os.fsync(out.fileno())
            return digest
        with self.fs.open(dst, "wb") as out:
            return copy_and_hash(src, out)

    def _write_small(self, dst: str, data: bytes) -> None:
        """Atomically replace a small file (sidecar, run record): temp name, fsync, rename."""
        if self.local:
            write_atomic(dst, data)
        else:
            # One PUT of a whole object is atomic on object stores; there is no rename to lean on.
            self.fs.pipe_file(dst, data)

    def _stage(self) -> str:
        tmp = self._p("tmp", uuid.uuid4().hex)
        home_mod.make_folder(self.fs, tmp)
        return tmp

    @contextlib.contextmanager
    def staging(self) -> Iterator[Path]:
        """A private local folder, removed at the end, for content about to be registered: in the
        store's own `tmp/` when local, so that `put_file`/`put_dir` commit what lies there by a rename;
        in the local cache for a remote store (uploaded as usual)."""
        base = Path(self._p("tmp")) if self.local else self.cache_dir.parent / "tmp"
        path = base / uuid.uuid4().hex
        path.mkdir(parents=True)
        try:
            yield path
        finally:
            shutil.rmtree(path, ignore_errors=True)

    def _in_staging(self, path: str) -> bool:
        """A regular file or directory inside this local store's `tmp/`: moved in, not copied."""
        if not self.local or os.path.islink(path):
            return False
        tmp = os.path.realpath(self._p("tmp")) + os.sep
        return os.path.realpath(path).startswith(tmp)

    def _discard(self, path: str) -> None:
        if self.local:
            shutil.rmtree(path, ignore_errors=True)
            return
        try:
            self.fs.rm(path, recursive=True)
        except FileNotFoundError:  # nothing there: one request, not an existence check and a removal
            pass

    def _commit_object(
        self, staged: str, artifact_id: str, entries: list[tuple[str, int, str]], present: bool
    ) -> None:
        """Put a fully written staging directory at its content address; `present`: an intact copy is
        already committed there (the staged one is dropped).

        Locally by one rename (a no-op when the object is there). Elsewhere each staged file is copied
        to its final key, replacing whatever a write killed before its sidecar left there; the
        sidecar, written after this returns, is what makes the artifact visible."""
        final = self.object_path(artifact_id)
        if self.local:
            home_mod.make_folder(self.fs, posixpath.dirname(final))
            try:
                os.rename(staged, final)
            except OSError as e:
                if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                    raise
                shutil.rmtree(staged, ignore_errors=True)  # same content already committed
            fsync_dir(posixpath.dirname(final))
        else:
            rels = [rel for rel, _, _ in entries]
            if not present:
                self._copy_files(staged, final, rels)
            self.fs.rm([posixpath.join(staged, rel) for rel in rels])  # by key: no listing first

    def _copy_files(self, src: str, dst: str, rels: list[str]) -> None:
        """Copy the files `rels` under `src` to the same relative keys under `dst` on a remote store
        (server side where the filesystem can: S3 CopyObject, GCS rewrite), all before returning."""
        if rels:
            srcs = [posixpath.join(src, rel) for rel in rels]
            dsts = [posixpath.join(dst, rel) for rel in rels]
            self.fs.copy(srcs, dsts)

    def _move_tree(self, src: str, dst: str) -> None:
        """Move a directory (or an object store's key prefix) to a new place: a rename locally; on an
        object store a copy of every key under it, then their removal."""
        if self.local:
            os.rename(src, dst)
            return
        base = src.rstrip("/") + "/"
        rels = [p[len(base) :] for p in self.fs.find(src) if p.startswith(base)]
        self._copy_files(src, dst, rels)
        self.fs.rm(src, recursive=True)

    def _stat(self, path: str) -> tuple[int, int | None]:
        """(size, mtime in ns) of a stored file; the mtime lets reads skip re-hashing unchanged files."""
        if self.local:
            st = os.stat(path)
            return st.st_size, st.st_mtime_ns
        info = self.fs.info(path)
        size = int(info["size"])
        modified = info.get("LastModified")  # s3fs's, which its `modified` would fetch in a second HEAD
        if not isinstance(modified, datetime):
            try:
                modified = self.fs.modified(path)
            except (NotImplementedError, OSError):
                return size, None
        return size, int(modified.timestamp() * 1_000_000) * 1000

    # ---------------------------------------------------------------- writing artifacts
    def _resolve_parents(
        self, parents: Iterable[ParentLike], hashed: ParentHashes | None = None
    ) -> list[ParentRef]:
        """Full ids of the parents, checked before any byte is written (UnknownParent otherwise)."""
        out = []
        for p in parents:
            ref = (
                p
                if isinstance(p, ParentRef)
                else ParentRef(id=p[0], role=p[1], attrs=p[2] if len(p) > 2 else {})
            )
            check_single_line("parent role", ref.role)
            try:
                full = self._lookup(ref.id)
                self._check_parent(full, (hashed or {}).get(full))
            except ArtifactNotFound:
                raise UnknownParent(ref.id) from None
            out.append(ref.model_copy(update={"id": full}))
        return out

    def _check_parent(self, artifact_id: str, hashed: Mapping[str, str] | None = None) -> None:
        """A parent edge vouches for the parent: its sidecar must pass its seal and its content its
        hash (memoized: a parent this process just read is not hashed again), unless `hashed` (the
        sha256 of each file, taken by the caller while reading it) covers every file. On a remote
        store the content is hashed when it is downloaded; here only its presence and sizes are checked."""
        record = self._load_sidecar(artifact_id)
        read = hashed is not None and all(hashed.get(f.path) == f.sha256 for f in record.files)
        if self.local and not read:
            self._verify(record, verify=True)
        else:
            self._check_present(record)

    def _check_present(self, record: ArtifactRecord) -> None:
        """Every recorded file is there with its recorded size; locally, as a regular file, and a
        directory holds nothing else (what a verified read checks besides the hashes)."""
        obj = self.object_path(record.id)
        for entry in record.files:
            full = posixpath.join(obj, entry.path)
            try:
                if self.local:
                    st = os.lstat(full)
                    if not stat.S_ISREG(st.st_mode):
                        raise CorruptArtifact(record.id, f"{entry.path} is not a regular file")
                    size = st.st_size
                else:
                    size, _ = self._stat(full)
            except FileNotFoundError:
                raise CorruptArtifact(record.id, f"{entry.path} is missing") from None
            if size != entry.size:
                raise CorruptArtifact(record.id, f"{entry.path} is {size} bytes, recorded {entry.size}")
        if self.local and record.layout == "dir":
            extra = self._unrecorded_files(record)
            if extra:
                raise CorruptArtifact(record.id, f"files not in its record: {', '.join(extra[:5])}")

    def _finish(
        self,
        staged: str,
        artifact_id: str,
        layout: str,
        entries: list[tuple[str, int, str]],
        meta: ArtifactMeta,
        parents: list[ParentRef],
    ) -> ArtifactRecord:
        """Commit the staged content and write its sidecar; `parents` are `meta.parents` as
        `_resolve_parents` checked them (full ids)."""
        existing = self._committed_record(artifact_id)
        present = existing is not None
        if existing is not None:
            if self.local and existing.layout == layout and self._swappable(existing, entries):
                self._swap_in(staged, existing, entries)
            elif not self._intact(existing):
                self._repair_with(staged, existing, layout, entries)
                present = False
                if layout == "file" and existing.files:  # the staged file now has the recorded name
                    entries = [(existing.files[0].path, entries[0][1], entries[0][2])]
        # no-op when present; restores a deleted or damaged object otherwise
        self._commit_object(staged, artifact_id, entries, present)
        if existing is not None:
            return existing  # written before: content addressing makes this idempotent
        obj = self.object_path(artifact_id)
        files = []
        for rel, size, digest in sorted(entries):
            st_size, mtime = self._stat(posixpath.join(obj, rel))
            if st_size != size:
                raise CorruptArtifact(artifact_id, f"{rel} is {st_size} bytes after commit, {size} written")
            files.append(FileEntry(path=rel, size=size, sha256=digest, mtime_ns=mtime))
        record, sidecar = seal_sidecar(
            ArtifactRecord(
                id=artifact_id,
                kind=meta.kind,
                name=meta.name,
                layout=layout,
                files=files,
                config=meta.config or {},
                parents=parents,
                code_version=code_version(),
                library_versions=meta.library_versions or {},
                flow_run_id=meta.flow_run_id,
                task_run_id=meta.task_run_id,
            )
        )
        self._write_small(self.sidecar_path(artifact_id), sidecar)
        self._note_change()
        return record

    def _committed_record(self, artifact_id: str) -> ArtifactRecord | None:
        """The record of an already committed artifact, or None.

        A sidecar that is unreadable or fails its seal counts as none, and the object it described is
        discarded: re-running the computation that produced the content is the one way to change an
        artifact's metadata, and this registration is that re-run."""
        try:
            return self._load_sidecar(artifact_id)
        except ArtifactNotFound:
            return None
        except CorruptArtifact:
            self._discard(self.object_path(artifact_id))
            return None

    def put_stream(
        self,
        src: BinaryIO,
        kind: str,
        name: str,
        config: dict[str, Any] | None = None,
        parents: Iterable[ParentLike] = (),
        *,
        filename: str,
        sha256: str | None = None,
        **provenance: Any,
    ) -> ArtifactRecord:
        """Store everything readable from `src` as a single-file artifact named `filename` inside it.

        `sha256`: what the caller hashed these bytes to; other bytes are refused (ValueError).
        `provenance`: library_versions, flow_run_id, task_run_id, and parent_hashes (see `_check_parent`)."""
        meta = ArtifactMeta.of(kind, name, config, parents, provenance)
        filename = _plain_name(filename)
        _check_labels(meta.kind, meta.name)
        refs = self._resolve_parents(meta.parents, meta.parent_hashes)
        staged = self._stage()
        try:
            digest, size = self._write_stream(src, posixpath.join(staged, filename))
            _expect({filename: sha256} if sha256 else {}, [(filename, size, digest)])
            return self._finish(staged, digest, "file", [(filename, size, digest)], meta, refs)
        except BaseException:  # a commit consumes the staged files; what a failure left is removed
            self._discard(staged)
            raise

    def put_file(
        self,
        src_path: str | os.PathLike[str],
        kind: str,
        name: str,
        config: dict[str, Any] | None = None,
        parents: Iterable[ParentLike] = (),
        *,
        filename: str | None = None,
        sha256: str | None = None,
        **provenance: Any,
    ) -> ArtifactRecord:
        """Store a local file (named `filename` in the store, by default its own name); its id equals
        `sha256sum src_path`.

        A file in this store's `staging()` is moved in, not copied, and with `sha256` (its hash as its
        writer or reader took it) not read again either."""
        src_path = os.fspath(src_path)
        filename = os.path.basename(src_path) if filename is None else filename
        if self._in_staging(src_path):
            meta = ArtifactMeta.of(kind, name, config, parents, provenance)
            return self._adopt(src_path, "file", meta, filename=filename, sha256=sha256)
        with open(src_path, "rb", buffering=0) as f:
            return self.put_stream(
                f, kind, name, config, parents, filename=filename, sha256=sha256, **provenance
            )

    def put_bytes(
        self,
        data: bytes,
        kind: str,
        name: str,
        config: dict[str, Any] | None = None,
        parents: Iterable[ParentLike] = (),
        *,
        filename: str = "data.bin",
        **kw: Any,
    ) -> ArtifactRecord:
        return self.put_stream(io.BytesIO(data), kind, name, config, parents, filename=filename, **kw)

    def put_json(
        self,
        obj: Any,
        kind: str,
        name: str,
        config: dict[str, Any] | None = None,
        parents: Iterable[ParentLike] = (),
        *,
        filename: str = "data.json",
        **kw: Any,
    ) -> ArtifactRecord:
        """Store a JSON document (pydantic models by their aliases); keys sorted so equal data has one id."""
        if isinstance(obj, BaseModel):
            obj = obj.model_dump(mode="json", by_alias=True)
        data = json.dumps(obj, sort_keys=True, indent=1, ensure_ascii=False).encode()
        return self.put_bytes(data, kind, name, config, parents, filename=filename, **kw)

    def put_dir(
        self,
        src_dir: str | os.PathLike[str],
        kind: str,
        name: str,
        config: dict[str, Any] | None = None,
        parents: Iterable[ParentLike] = (),
        *,
        hashes: Mapping[str, str] | None = None,
        **provenance: Any,
    ) -> ArtifactRecord:
        """Store a local directory tree (dataset, sharded checkpoint, adapter) as one artifact.

        Only regular files inside the folder are stored (see `_members`): a link to a file inside it
        as that file's content; a link leading out, a symlinked directory, a FIFO or a device is
        refused naming the member, before anything is written. Each member is read up to the size it
        was listed with, so a file that grows meanwhile is refused rather than copied without end.
        A directory in this store's `staging()` is moved in; `hashes` (member -> sha256 as its writer
        or reader took it) spare reading those members again there, and must match elsewhere.
        `provenance`: as for `put_stream`.
        """
        meta = ArtifactMeta.of(kind, name, config, parents, provenance)
        src_dir = os.path.abspath(os.fspath(src_dir))
        if not os.path.isdir(src_dir):
            raise NotADirectoryError(src_dir)
        _check_labels(meta.kind, meta.name)
        if self._in_staging(src_dir):
            return self._adopt(src_dir, "dir", meta, hashes=hashes)
        members = _members(src_dir)
        if not members:
            raise ValueError(f"{src_dir} contains no files; an empty artifact is almost certainly a bug")
        refs = self._resolve_parents(meta.parents, meta.parent_hashes)
        staged = self._stage()
        try:
            entries = []
            for rel, full in members:
                dst = posixpath.join(staged, rel)
                home_mod.make_folder(self.fs, posixpath.dirname(dst))
                f, listed = _open_member(full, rel, src_dir)
                with f:
                    digest, size = self._write_stream(_Bounded(f, listed + 1), dst)
                if size != listed:
                    raise ValueError(
                        f"{rel} in {src_dir} changed while it was being stored; run the command again"
                    )
                entries.append((rel, size, digest))
            _expect(hashes or {}, entries)
            if self.local:
                for d in {posixpath.dirname(posixpath.join(staged, rel)) for rel, _ in members}:
                    fsync_dir(d)
            return self._finish(staged, manifest_id(entries), "dir", entries, meta, refs)
        except BaseException:  # a commit consumes the staged files; what a failure left is removed
            self._discard(staged)
            raise

    def _adopt(
        self,
        src: str,
        layout: str,
        meta: ArtifactMeta,
        *,
        filename: str | None = None,
        sha256: str | None = None,
        hashes: Mapping[str, str] | None = None,
    ) -> ArtifactRecord:
        """Commit a file or folder of `staging()` by renaming it (same filesystem, no copy); members
        without a hash from `hashes`/`sha256` are hashed here. Each file is fsynced before the commit."""
        _check_labels(meta.kind, meta.name)
        refs = self._resolve_parents(meta.parents, meta.parent_hashes)
        staged = self._p("tmp", uuid.uuid4().hex)
        if layout == "file":
            filename = _plain_name(filename or os.path.basename(src))
            hashes = {filename: sha256} if sha256 else {}
            os.mkdir(staged)
            os.rename(src, posixpath.join(staged, filename))
        else:
            os.rename(src, staged)
        try:
            entries = []
            for rel, full in _members(staged):
                st = os.lstat(full)
                if not stat.S_ISREG(st.st_mode):
                    raise ValueError(f"{rel} in {src} is not a regular file")
                fsync_file(full)
                entries.append((rel, st.st_size, (hashes or {}).get(rel) or hash_file(full)))
            if not entries:
                raise ValueError(f"{src} contains no files; an empty artifact is almost certainly a bug")
            for d in {posixpath.dirname(posixpath.join(staged, rel)) for rel, _, _ in entries}:
                fsync_dir(d)
            artifact_id = entries[0][2] if layout == "file" else manifest_id(entries)
            return self._finish(staged, artifact_id, layout, entries, meta, refs)
        finally:
            self._discard(staged)

    # ---------------------------------------------------------------- reading
    def resolve(self, id_or_prefix: str) -> str:
        """Full id for an id or a prefix of at least 6 hex characters."""
        prefix = _valid_id(id_or_prefix)
        if len(prefix) == 64:
            if self.fs.exists(self.sidecar_path(prefix)):
                return prefix
            raise ArtifactNotFound(f"no artifact {prefix}")
        shard = self._p("objects", prefix[:2])
        try:
            names = self.fs.ls(shard, detail=False)
        except FileNotFoundError:
            names = []
        hits = sorted(
            b[:-5]
            for b in map(posixpath.basename, names)
            if b.endswith(".json") and b.startswith(prefix) and len(b) == 69
        )
        if not hits:
            raise ArtifactNotFound(f"no artifact with id prefix {prefix}")
        if len(hits) > 1:
            raise AmbiguousId(prefix, hits)
        return hits[0]

    def _load_sidecar(self, artifact_id: str) -> ArtifactRecord:
        try:
            record = parse_sidecar(self.fs.cat_file(self.sidecar_path(artifact_id)))
        except FileNotFoundError:
            raise ArtifactNotFound(f"no artifact {artifact_id}") from None
        except SealBroken as e:
            raise CorruptArtifact(
                artifact_id,
                f"sidecar metadata was edited after registration: {e} (its kind, name, config and "
                "lineage are not trusted; re-run the computation that produced it to change them)",
            ) from None
        except PathEscape as e:
            raise CorruptArtifact(artifact_id, f"sidecar names a path outside the artifact: {e}") from None
        except ValueError as e:
            raise CorruptArtifact(artifact_id, f"unreadable sidecar: {e}") from None
        expected = (
            record.files[0].sha256
            if record.layout == "file" and len(record.files) == 1
            else (manifest_id((f.path, f.size, f.sha256) for f in record.files))
        )
        if record.id != artifact_id or expected != artifact_id:
            raise CorruptArtifact(artifact_id, "sidecar does not describe this id")
        if not record.sealed and self.unsealed_guard is not None:
            self.unsealed_guard(record)
        return record

    def _lookup(self, id_or_prefix: str) -> str:
        """A full id as it is, a prefix resolved: for a caller that reads the sidecar next, whose
        absence is ArtifactNotFound as `resolve`'s check would be (one request fewer remotely)."""
        prefix = _valid_id(id_or_prefix)
        return prefix if len(prefix) == 64 else self.resolve(prefix)

    def get(self, id_or_prefix: str) -> ArtifactRecord:
        """The record of a committed artifact (metadata only; use `path` to reach the content)."""
        return self._load_sidecar(self._lookup(id_or_prefix))

    def exists(self, id_or_prefix: str) -> bool:
        try:
            self.resolve(id_or_prefix)
        except (ArtifactNotFound, AmbiguousId):
            return False
        return True

    def _changed(self, record: ArtifactRecord) -> dict[str, int | None]:
        """Stored files whose size or mtime moved since they were recorded: path -> current mtime."""
        obj, changed = self.object_path(record.id), {}
        for entry in record.files:
            try:
                size, mtime = self._stat(posixpath.join(obj, entry.path))
            except FileNotFoundError:
                raise CorruptArtifact(record.id, f"{entry.path} is missing") from None
            if size != entry.size or mtime != entry.mtime_ns:
                changed[entry.path] = mtime
        return changed

    def _refresh_mtimes(self, record: ArtifactRecord, mtimes: dict[str, int | None]) -> None:
        """Record new mtimes of files whose content was just re-verified (so `verify=False` reads do
        not re-hash them). The sidecar's JSON is patched in place: mtimes are outside the seal, and
        everything the seal covers keeps the exact values it was sealed with."""
        if not mtimes:
            return
        for entry in record.files:
            entry.mtime_ns = mtimes.get(entry.path, entry.mtime_ns)
        path = self.sidecar_path(record.id)
        try:
            doc = json.loads(self.fs.cat_file(path))
        except (FileNotFoundError, ValueError):
            return  # gone or replaced meanwhile: the next read sees whatever is there now
        for entry in doc.get("files") or []:
            if isinstance(entry, dict) and entry.get("path") in mtimes:
                entry["mtime_ns"] = mtimes[entry["path"]]
        self._write_small(path, json.dumps(doc, indent=1, ensure_ascii=False).encode())

    def _swap_in(self, staged: str, record: ArtifactRecord, entries: list[tuple[str, int, str]]) -> None:
        """The same content again, freshly written and hashed: it replaces the stored copy file by file
        (each rename atomic, the bytes equal either way), so a damaged copy is repaired without first
        reading it; files the record lacks are removed."""
        obj, targets = self.object_path(record.id), self._targets(record, entries)
        mtimes = {}
        for rel, _, _ in entries:
            dst = posixpath.join(obj, targets[rel])
            os.replace(posixpath.join(staged, rel), dst)
            mtimes[targets[rel]] = os.stat(dst).st_mtime_ns
        for rel in self._unrecorded_files(record) if record.layout == "dir" else []:
            full = posixpath.join(obj, rel)
            shutil.rmtree(full) if os.path.isdir(full) and not os.path.islink(full) else os.unlink(full)
        for d in {posixpath.dirname(posixpath.join(obj, rel)) for rel in mtimes}:
            fsync_dir(d)
        self._refresh_mtimes(record, mtimes)

    def _swappable(self, record: ArtifactRecord, entries: list[tuple[str, int, str]]) -> bool:
        """Whether `_swap_in` can put every file in place: its folders are real folders of the object
        (a symlink could lead the rename outside the store) and nothing but a file is in its way."""

        def real_dir(path: str) -> bool:
            return os.path.isdir(path) and not os.path.islink(path)

        obj = self.object_path(record.id)
        for rel in self._targets(record, entries).values():
            parts = rel.split("/")
            if not all(real_dir(posixpath.join(obj, *parts[:i])) for i in range(len(parts))):
                return False
            if os.path.isdir(posixpath.join(obj, rel)):
                return False
        return True

    @staticmethod
    def _targets(record: ArtifactRecord, entries: list[tuple[str, int, str]]) -> dict[str, str]:
        """Staged name -> stored name: a single file keeps the name its sidecar recorded."""
        if record.layout == "file":
            return {entries[0][0]: record.files[0].path}
        return {rel: rel for rel, _, _ in entries}

    def _repair_with(self, staged: str, record: ArtifactRecord, layout: str, entries: list) -> None:
        """The same content again, over a damaged or missing copy: the fresh bytes replace it.

        A single file keeps the name its sidecar recorded (the id covers bytes, not names).
        """
        if layout == "file" and record.files and entries[0][0] != record.files[0].path:
            self.fs.mv(posixpath.join(staged, entries[0][0]), posixpath.join(staged, record.files[0].path))
        self._discard(self.object_path(record.id))

    def _intact(self, record: ArtifactRecord) -> bool:
        try:
            self._verify(record, verify=True, memo=False)
        except (CorruptArtifact, OSError):
            return False
        return True

    def _verify(self, record: ArtifactRecord, verify: bool, memo: bool = True, refresh: bool = True) -> None:
        """Re-hash every file when `verify` (see `_hash_local` for the in-process memo), else only
        those whose size or mtime moved since they were recorded. A verified local directory must
        also hold no file beyond its record: a consumer that lists it would read what no id covers."""
        changed = self._changed(record)
        obj = self.object_path(record.id)
        for entry in record.files:
            if not verify and entry.path not in changed:
                continue
            full = posixpath.join(obj, entry.path)
            if self.local:
                digest, size = _hash_local(full, entry.sha256, memo)
            else:
                with self.fs.open(full, "rb") as f:
                    digest, size = hash_stream(f)
            if size != entry.size or digest != entry.sha256:
                raise CorruptArtifact(
                    record.id,
                    f"{entry.path}: {size} bytes, sha256 {digest[:12]}…, "
                    f"recorded {entry.size} bytes, sha256 {entry.sha256[:12]}…",
                )
        if verify and self.local and record.layout == "dir":
            extra = self._unrecorded_files(record)
            if extra:
                raise CorruptArtifact(record.id, f"files not in its record: {', '.join(extra[:5])}")
        if refresh:
            self._refresh_mtimes(record, changed)

    def _unrecorded_files(self, record: ArtifactRecord) -> list[str]:
        """Files (or links, or anything else) inside a local directory artifact that its record lacks."""
        obj, recorded, extra = self.object_path(record.id), {f.path for f in record.files}, []
        for dirpath, dirnames, filenames in os.walk(obj):
            for name in filenames + [d for d in dirnames if os.path.islink(os.path.join(dirpath, d))]:
                rel = os.path.relpath(os.path.join(dirpath, name), obj).replace(os.sep, "/")
                if rel not in recorded:
                    extra.append(rel)
        return sorted(extra)

    def audit(self, id_or_prefix: str) -> IntegrityVerdict:
        """Full check of one artifact (`capvector verify`): the sidecar against its seal and every
        byte against the id, read from the store itself (not a cache, no memo), writing nothing."""
        try:
            artifact_id = self.resolve(id_or_prefix)
        except (ArtifactNotFound, AmbiguousId, MalformedId) as e:
            return IntegrityVerdict(id=str(id_or_prefix), status="missing", detail=str(e))
        try:
            record = self._load_sidecar(artifact_id)
        except ArtifactNotFound as e:
            return IntegrityVerdict(id=artifact_id, status="missing", detail=str(e))
        except CorruptArtifact as e:
            return IntegrityVerdict(id=artifact_id, status="corrupt", detail=str(e))
        try:
            self._verify(record, verify=True, memo=False, refresh=False)
        except CorruptArtifact as e:
            return IntegrityVerdict(id=artifact_id, status="corrupt", detail=str(e), size=record.size)
        except OSError as e:
            detail = f"artifact {artifact_id} is unreadable: {e}"
            return IntegrityVerdict(id=artifact_id, status="corrupt", detail=detail, size=record.size)
        if record.sealed:
            return IntegrityVerdict(id=artifact_id, status="ok", size=record.size)
        detail = "sidecar written before sealing: its metadata is not protected"
        return IntegrityVerdict(id=artifact_id, status="unsealed", detail=detail, size=record.size)

    def path(self, id_or_prefix: str, verify: bool = True, member: str | None = None) -> Path:
        """Local path of a verified artifact: the file, the directory, or one `member` of a directory.

        `verify` (the default, and what every input of a registered computation must use): every file
        of the artifact is re-hashed (memoized within this process, see `_hash_local`), so changed
        bytes raise CorruptArtifact naming the id. `verify=False` only compares sizes and mtimes,
        which bit rot and copies that keep times pass: for display, never for computing.
        Remote stores are materialised into the local cache first (downloads are always hashed).
        """
        record = self.get(id_or_prefix)
        if member is not None:
            member = safe_relpath(member)
            if member not in {f.path for f in record.files}:
                raise ArtifactNotFound(f"artifact {record.id} has no member {member!r}")
        if self.local:
            self._verify(record, verify)
            base = Path(self.object_path(record.id))
        else:
            base = self._materialize(record, verify)
        if member is not None:
            return base / member
        return base / record.files[0].path if record.layout == "file" else base

    def stream_path(self, id_or_prefix: str) -> tuple[Path, ArtifactRecord]:
        """(local path, record) of an artifact that the caller hashes as it reads it, then checks with
        `check_read` before it registers anything computed from it: one pass over the bytes instead
        of a verified `path()` and a read. Here only the seal, sizes and file types are checked.
        A remote artifact is materialised (hashed while downloading, as `path()` does)."""
        record = self.get(id_or_prefix)
        if not self.local:
            return self.path(record.id), record
        self._check_present(record)
        base = Path(self.object_path(record.id))
        return (base / record.files[0].path if record.layout == "file" else base), record

    def check_read(self, record: ArtifactRecord, path: Path, hashes: Mapping[Path, str]) -> dict[str, str]:
        """Check an artifact read from `stream_path`'s `path` against its id: `hashes` (file path ->
        sha256 taken while reading it) for the files read, a hash now for the others; also that no
        file was swapped for a link or added meanwhile. Raises CorruptArtifact naming the id; returns
        member -> sha256 (the `parent_hashes` entry of a registration computed from it)."""
        base = path.parent if record.layout == "file" else path
        self._check_present(record)
        out = {}
        for entry in record.files:
            full = base / entry.path
            digest = hashes.get(full) or _hash_local(str(full), entry.sha256)[0]
            if digest != entry.sha256:
                raise CorruptArtifact(
                    record.id,
                    f"{entry.path}: read as sha256 {digest[:12]}…, recorded {entry.sha256[:12]}…",
                )
            out[entry.path] = digest
        return out

    def _materialize(self, record: ArtifactRecord, verify: bool) -> Path:
        """Download a remote artifact into the cache, hashing as it streams.

        A cached copy is reused while the remote files keep their recorded size and mtime (one metadata
        call per file, no download); `verify` re-hashes the cached copy too.
        """
        final = self.cache_dir / record.id
        changed = self._changed(record)  # a remote file that moved invalidates the cached copy
        if final.is_dir() and not changed:
            intact = all(
                (final / f.path).is_file() and (final / f.path).stat().st_size == f.size for f in record.files
            )
            if intact and verify:
                intact = all(_hash_local(str(final / f.path), f.sha256)[0] == f.sha256 for f in record.files)
            if intact:
                return final
        shutil.rmtree(final, ignore_errors=True)
        staged = self.cache_dir / f".tmp-{uuid.uuid4().hex}"
        try:
            for f in record.files:
                dst = staged / f.path
                dst.parent.mkdir(parents=True, exist_ok=True)
                try:
                    src = self.fs.open(posixpath.join(self.object_path(record.id), f.path), "rb")
                except FileNotFoundError:
                    raise CorruptArtifact(record.id, f"{f.path} is missing") from None
                with src, open(dst, "wb") as out:
                    digest, size = copy_and_hash(src, out)
                if digest != f.sha256 or size != f.size:
                    raise CorruptArtifact(record.id, f"{f.path} does not match its recorded sha256/size")
            try:
                os.rename(staged, final)
            except OSError:
                if not final.is_dir():
                    raise  # otherwise a concurrent reader put the same verified copy there first
            self._refresh_mtimes(record, changed)
            return final
        finally:
            shutil.rmtree(staged, ignore_errors=True)

    def read_bytes(self, id_or_prefix: str, member: str | None = None) -> bytes:
        """Bytes of a small file artifact or member, hashed on every read (they are in memory anyway)."""
        record = self.get(id_or_prefix)
        rel = safe_relpath(member) if member is not None else record.files[0].path
        entry = next((f for f in record.files if f.path == rel), None)
        if entry is None:
            raise ArtifactNotFound(f"artifact {record.id} has no member {rel!r}")
        try:
            data = self.fs.cat_file(posixpath.join(self.object_path(record.id), rel))
        except FileNotFoundError:
            raise CorruptArtifact(record.id, f"{rel} is missing") from None
        digest, size = hash_stream(io.BytesIO(data))
        if digest != entry.sha256 or size != entry.size:
            raise CorruptArtifact(record.id, f"{rel} does not match its recorded sha256/size")
        return data

    def open_json(self, id_or_prefix: str, member: str | None = None) -> Any:
        return json.loads(self.read_bytes(id_or_prefix, member))

    def iter_ids(self) -> Iterator[str]:
        """Ids of all committed artifacts (those with a sidecar), in no particular order."""
        if self.local:
            objects = self._p("objects")
            for shard in os.scandir(objects):
                if shard.is_dir():
                    for e in os.scandir(shard.path):
                        if e.name.endswith(".json") and PREFIX_RE.match(e.name[:-5]) and len(e.name) == 69:
                            yield e.name[:-5]
            return
        for p in self.fs.glob(self._p("objects", "*", "*.json")):
            b = posixpath.basename(p)
            if len(b) == 69 and PREFIX_RE.match(b[:-5]):
                yield b[:-5]

    def iter_records(self) -> Iterator[ArtifactRecord]:
        for artifact_id in self.iter_ids():
            yield self._load_sidecar(artifact_id)

    # ---------------------------------------------------------------- runs
    def _run_path(self, flow_run_id: str) -> str:
        if not RUN_ID_RE.match(flow_run_id):
            raise PathEscape(f"flow run id {flow_run_id!r} is not a plain name")
        return self._p("runs", f"{flow_run_id}.json")

    def put_run(self, run: RunRecord) -> None:
        """Create or update a run record (runs change state, so they are replaced, not content-addressed)."""
        home_mod.make_folder(self.fs, self._p("runs"))
        self._write_small(self._run_path(run.flow_run_id), run.model_dump_json(indent=1).encode())
        self._note_change()

    def _note_change(self) -> None:
        """A remote store's change token, rewritten after each commit (the sidecar or run record is
        already there): a catalogue that read the token before listing sees a new one after any commit
        its listing may have missed. A local store's directory times do this job (catalogue
        .store_fingerprint). Each writer writes a fresh random token, so racing writers cannot
        leave the one a reader saw."""
        if not self.local:
            self.fs.pipe_file(self._p(CHANGES), uuid.uuid4().hex.encode())

    def change_token(self) -> str | None:
        """A remote store's current change token; None before its first commit by this version."""
        try:
            return self.fs.cat_file(self._p(CHANGES)).decode()
        except FileNotFoundError:
            return None

    # ---------------------------------------------------------------- content-cache index
    def index_entry_path(self, key: str) -> str:
        """`index/<key[:2]>/<key>.json` of a step cache key (64 hex characters, else PathEscape)."""
        if not isinstance(key, str) or not KEY_RE.match(key):
            raise PathEscape(f"cache key {key!r} is not 64 hex characters")
        return self._p(INDEX, key[:2], f"{key}.json")

    def put_index_entry(self, key: str, data: bytes) -> None:
        """Write (or replace) the index object of a cache key whole: a temp name and a rename locally,
        one PUT on an object store. One object per key: writers of different keys never meet, and two
        writers of one key write the same answer (its lock, capvector.tasks.runtime.caching.step_lock,
        holds one machine's; on two machines the last PUT stands, each naming a verified artifact)."""
        path = self.index_entry_path(key)
        home_mod.make_folder(self.fs, posixpath.dirname(path))
        self._write_small(path, data)

    def index_entry(self, key: str) -> bytes | None:
        """The bytes of a cache key's index object (one GET, no listing), None when there is none.
        ValueError when it is larger than any entry (INDEX_ENTRY_MAX): it is not read."""
        path = self.index_entry_path(key)
        try:
            data = self.fs.cat_file(path, start=0, end=INDEX_ENTRY_MAX + 1)
        except FileNotFoundError:
            return None
        if len(data) > INDEX_ENTRY_MAX:
            raise ValueError(f"{path} is over {INDEX_ENTRY_MAX} bytes: not an index entry")
        return data

    def iter_index_keys(self) -> list[str]:
        """The key of every index object, sorted, from one listing of `index/*/*.json` (for `verify
        --all`). An object that is not `<key[:2]>/<key>.json` is listed as its path under the store
        (`index/…`), which no key matches, so a caller can name it instead of reading another key."""
        out = []
        for p in self.fs.glob(self._p(INDEX, "*", "*.json")):
            shard, name = posixpath.basename(posixpath.dirname(p)), posixpath.basename(p)[: -len(".json")]
            out.append(name if KEY_RE.match(name) and shard == name[:2] else f"{INDEX}/{shard}/{name}.json")
        return sorted(out)

    def iter_runs(self) -> Iterator[RunRecord]:
        for p in sorted(self.fs.glob(self._p("runs", "*.json"))):
            yield RunRecord.model_validate_json(self.fs.cat_file(p))

    # ---------------------------------------------------------------- garbage
    def referenced_parents(self) -> set[str]:
        """Every id that some sidecar names as a parent, read from the raw JSON (a sidecar that fails
        its seal still names its parents: gc must not delete what it may point at)."""
        out: set[str] = set()
        for artifact_id in self.iter_ids():
            try:
                doc = json.loads(self.fs.cat_file(self.sidecar_path(artifact_id)))
                out.update(
                    str(p["id"]) for p in doc.get("parents") or [] if isinstance(p, dict) and "id" in p
                )
            except (OSError, ValueError, AttributeError, TypeError):
                continue
        return out

    def gc(self, older_than_s: float = 3600.0, referenced: Iterable[str] = ()) -> "GcResult":
        """Remove staging leftovers (never committed) older than `older_than_s`; move committed-looking
        objects without a sidecar aside, never delete them.

        An object directory without a sidecar is a write killed between its rename and its sidecar, or
        an artifact whose sidecar was lost: its bytes may be the only copy. One that a sidecar
        (`referenced_parents`) or the caller (`referenced`: the catalogue's edges) names as a parent
        is left where it is (`kept`); any other is moved to `quarantine/<time>/<id>` under the store
        root (`quarantined`), for a person to inspect, restore or delete.
        The age guard keeps gc from touching a write that another process is committing right now.
        """
        cutoff = time.time() - older_than_s
        result = GcResult()
        parents = set(referenced) | self.referenced_parents()
        if self.fs.exists(self._p("tmp")):
            for p in self.fs.ls(self._p("tmp"), detail=False):
                if self._age_ts(p) <= cutoff:
                    self._discard(p)
                    result.removed.append(p)
        stamp = datetime.now().strftime("%Y%m%dT%H%M%S") + f"-{uuid.uuid4().hex[:6]}"
        for shard in self.fs.ls(self._p("objects"), detail=False):
            for p in self.fs.ls(shard, detail=False):
                if p.endswith(".json") or self.fs.exists(p + ".json") or self._age_ts(p) > cutoff:
                    continue
                artifact_id = posixpath.basename(p.rstrip("/"))
                if len(artifact_id) != 64 or not PREFIX_RE.match(artifact_id):  # a sidecar's temp file
                    self._discard(p)
                    result.removed.append(p)
                    continue
                if artifact_id in parents:
                    result.kept.append(artifact_id)
                    continue
                dest = self._p("quarantine", stamp, artifact_id)
                home_mod.make_folder(self.fs, posixpath.dirname(dest))
                self._move_tree(p, dest)
                result.quarantined.append(dest)
        return result

    def _age_ts(self, path: str) -> float:
        if self.local:
            return os.stat(path).st_mtime
        try:
            return self.fs.modified(path).timestamp()
        except (NotImplementedError, OSError):
            pass
        # A pseudo-directory of an object store has no time of its own: that of its newest key (a
        # write in progress has just put one there), or old when it holds none.
        newest = 0.0
        with contextlib.suppress(NotImplementedError, OSError):
            for f in self.fs.find(path):
                with contextlib.suppress(NotImplementedError, OSError):
                    newest = max(newest, self.fs.modified(f).timestamp())
        return newest
