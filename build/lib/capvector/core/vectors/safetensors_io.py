"""Streaming reader and writer for safetensors checkpoints, single-file or sharded (Hugging Face layout).

Why not `safetensors.torch.load_file`/`save_file`: the first memory-maps whole files (touched pages count
towards the process's resident memory), the second needs every tensor in memory at once. Checkpoints of a
7B policy do not fit that, so this module parses the (simple) format itself: an 8-byte little-endian header
length, a JSON header `{name: {dtype, shape, data_offsets}, "__metadata__": {str: str}}`, then raw
little-endian bytes. Reading copies one tensor (or a piece of it) at a time into an owned numpy buffer
(`readinto`); writing computes every header up front from names, shapes and dtypes, then streams tensor
data in that order. Bytes are numpy arrays (`STORAGE`); torch tensors only where a caller asks for them.
Before any tensor byte is read, each header is checked as the safetensors library checks it (then opened by
the library as the reference), and every file an index names must lie inside its folder: what a checkpoint
id stands for is then exactly the bytes the store copied.

Layouts understood by `Checkpoint`:
- a `.safetensors` file;
- a directory with `model.safetensors.index.json` (`{"metadata": {...}, "weight_map": {name: shard}}`);
- a directory with a single `model.safetensors`.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import math
import os
import secrets
import shutil
import stat
import struct
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from safetensors import SafetensorError, safe_open

from capvector.durable import fsync_dir, fsync_files

if TYPE_CHECKING:
    import torch

INDEX_NAME = "model.safetensors.index.json"
SINGLE_NAME = "model.safetensors"
DEFAULT_MAX_SHARD_BYTES = 2 << 30
WRITEBACK_BYTES = 32 << 20  # a writer queues its file for writeback every this many bytes
HEADER_LIMIT = 100_000_000  # the safetensors library's upper bound on header size

# dtype -> the numpy dtype its bytes are read as. No numpy type for bfloat16 and float8: their bits, as
# unsigned integers (vector_ops converts them). Torch is imported only by the torch-facing methods: it
# takes seconds, which a CLI command that never builds a tensor should not pay.
STORAGE: dict[str, np.dtype] = {
    name: np.dtype(code)
    for name, code in {
        "F64": "<f8",
        "F32": "<f4",
        "F16": "<f2",
        "BF16": "<u2",
        "F8_E4M3": "u1",
        "F8_E5M2": "u1",
        "I64": "<i8",
        "I32": "<i4",
        "I16": "<i2",
        "I8": "i1",
        "U8": "u1",
        "BOOL": "?",
    }.items()
}
FLOATS = frozenset({"F64", "F32", "F16", "BF16", "F8_E4M3", "F8_E5M2"})
_TORCH_NAMES = {
    "F64": "float64",
    "F32": "float32",
    "F16": "float16",
    "BF16": "bfloat16",
    "F8_E4M3": "float8_e4m3fn",
    "F8_E5M2": "float8_e5m2",
    "I64": "int64",
    "I32": "int32",
    "I16": "int16",
    "I8": "int8",
    "U8": "uint8",
    "BOOL": "bool",
}


def torch_dtype(name: str) -> torch.dtype:
    import torch

    return getattr(torch, _TORCH_NAMES[name])


def dtype_name(dtype: object) -> str | None:
    """safetensors name of a torch dtype (or of a name already), None if it has none."""
    if isinstance(dtype, str):
        return dtype if dtype in STORAGE else None
    return next((k for k, v in _TORCH_NAMES.items() if str(dtype) == f"torch.{v}"), None)


class CheckpointError(ValueError):
    """A checkpoint is malformed, incomplete, or does not fit the operation asked of it."""


@dataclass(frozen=True)
class TensorSpec:
    """Where one tensor lives and what it is, read from a header without touching its data."""

    name: str
    dtype: str  # safetensors spelling, e.g. "BF16"
    shape: tuple[int, ...]
    file: Path
    begin: int  # absolute byte offset in `file`
    end: int

    @property
    def nbytes(self) -> int:
        return self.end - self.begin

    @property
    def torch_dtype(self) -> torch.dtype:
        return torch_dtype(self.dtype)

    @property
    def itemsize(self) -> int:
        return STORAGE[self.dtype].itemsize

    @property
    def is_float(self) -> bool:
        return self.dtype in FLOATS


def _regular_size(path: Path) -> int:
    """Size of a regular file: a FIFO or device would block or never end, a directory cannot be read."""
    try:
        st = path.stat()
    except FileNotFoundError:
        raise CheckpointError(f"missing file: {path}") from None
    if not stat.S_ISREG(st.st_mode):
        raise CheckpointError(f"not a regular file: {path}")
    return st.st_size


def _read_header(path: Path) -> tuple[dict, int, int]:
    """(header, offset where tensor data starts, file size); errors never quote the file's bytes."""
    size = _regular_size(path)
    if size < 8:
        raise CheckpointError(f"truncated file (shorter than the 8-byte header length): {path}")
    with open(path, "rb") as f:
        n = int.from_bytes(f.read(8), "little")
        if n > HEADER_LIMIT:
            raise CheckpointError(f"not a safetensors file (header length over {HEADER_LIMIT} bytes): {path}")
        if 8 + n > size:
            raise CheckpointError(f"truncated file: header length {n} exceeds file size {size}: {path}")
        raw = f.read(n)
    try:
        header = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise CheckpointError(
            f"corrupt safetensors header in {path}: not UTF-8 at byte {8 + e.start}"
        ) from None
    except (json.JSONDecodeError, RecursionError) as e:
        raise CheckpointError(
            f"corrupt safetensors header in {path}: {str(e) or 'nested too deeply'}"
        ) from None
    if not isinstance(header, dict):
        raise CheckpointError(f"corrupt safetensors header in {path}: not a JSON object")
    return header, 8 + n, size


def _show(value: object, limit: int = 60) -> str:
    text = json.dumps(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _is_index(v: object) -> bool:
    return type(v) is int and v >= 0  # not bool, not float: what the format's usize fields take


def _specs_of_file(path: Path) -> tuple[dict[str, TensorSpec], dict[str, str]]:
    """Tensor specs and metadata of one file, refused in one line unless the safetensors library loads it.

    The checks name the tensor at fault and run before any tensor byte is read, so reads stay inside the
    file and inside each tensor; the library then opens the file (headers only, ~1 ms) as the reference
    for anything they do not cover (e.g. JSON that Python's parser takes and serde refuses).
    """
    header, start, size = _read_header(path)
    meta = header.pop("__metadata__", None)
    if meta is None:
        meta = {}
    elif not isinstance(meta, dict) or not all(isinstance(v, str) for v in meta.values()):
        raise CheckpointError(
            f"corrupt safetensors header in {path}: __metadata__ must map strings to strings"
        )

    def bad(name: str, problem: str) -> CheckpointError:
        return CheckpointError(f"tensor {name!r} in {path}: {problem}")

    spans = []
    for name, v in header.items():
        if not isinstance(v, dict):
            raise bad(name, f"its header entry is {_show(v)}, not an object")
        for field in ("dtype", "shape", "data_offsets"):
            if field not in v:
                raise bad(name, f"its header entry has no {field!r}")
        dtype, shape, offsets = v["dtype"], v["shape"], v["data_offsets"]
        if not isinstance(dtype, str) or dtype not in STORAGE:
            raise bad(name, f"unsupported dtype {_show(dtype)}")
        if not isinstance(shape, list) or not all(_is_index(d) for d in shape):
            raise bad(name, f"shape must be a list of non-negative integers, not {_show(shape)}")
        if not isinstance(offsets, list) or len(offsets) != 2 or not all(_is_index(o) for o in offsets):
            raise bad(name, f"data_offsets must be two non-negative integers, not {_show(offsets)}")
        b, e = offsets
        if e < b:
            raise bad(name, f"data_offsets {_show(offsets)} end before they begin")
        need = math.prod(shape) * STORAGE[dtype].itemsize
        if e - b != need:
            raise bad(
                name, f"data_offsets {_show(offsets)} hold {e - b} bytes, {dtype} {_show(shape)} takes {need}"
            )
        spans.append((b, e, name))
    spans.sort()  # the library's order: by (begin, end); tensors must tile the data from 0 without holes
    end, prev = 0, None
    for b, e, name in spans:
        if b < end:
            raise bad(name, f"data_offsets {_show([b, e])} overlap tensor {prev!r}, which ends at {end}")
        if b > end:
            after = (
                f"after tensor {prev!r}, which ends at {end}"
                if prev is not None
                else "before it (data starts at 0)"
            )
            raise bad(name, f"data_offsets {_show([b, e])} leave a hole of {b - end} bytes {after}")
        end, prev = e, name
    if start + end > size:
        e, name = next((e, n) for _, e, n in spans if start + e > size)
        raise bad(name, f"truncated file: the tensor's data ends at byte {start + e}, the file has {size}")
    if start + end < size:
        raise CheckpointError(
            f"{path} has {size - start - end} bytes after its last tensor (the format allows none)"
        )
    try:
        with safe_open(path, "np"):
            pass
    except SafetensorError as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise CheckpointError(f"{path}: the safetensors library refuses it: {first[:200]}") from None
    span = {name: (b, e) for b, e, name in spans}
    specs = {  # header order, as before: for files we write it is also the storage order
        name: TensorSpec(
            name, v["dtype"], tuple(v["shape"]), path, start + span[name][0], start + span[name][1]
        )
        for name, v in header.items()
    }
    return specs, meta


def _inside(folder: Path, name: object, where: Path, what: str = "shard") -> Path:
    """`folder / name`, refused unless its real path (symlinks resolved) lies inside the folder's real path.

    Checked before anything is opened: an index may name any path, and a checkpoint's id must not depend on
    files the store does not copy (nor may an error quote them).
    """
    if not isinstance(name, str) or not name or "\0" in name:
        raise CheckpointError(f"{where}: {what} {name!r} is not a file name")
    if os.path.isabs(name):
        raise CheckpointError(f"{where}: {what} {name!r} is an absolute path, outside the checkpoint folder")
    path = folder / name
    try:
        root, real = folder.resolve(strict=True), path.resolve()
    except (OSError, RuntimeError):  # a symlink loop
        raise CheckpointError(f"{where}: {what} {name!r} cannot be resolved (a symlink loop?)") from None
    if real == root or not real.is_relative_to(root):
        raise CheckpointError(
            f"{where}: {what} {name!r} lies outside the checkpoint folder (after resolving '..' and symlinks)"
        )
    return path


class Checkpoint:
    """A validated, lazily read safetensors checkpoint (file, sharded directory, or directory with one file).

    Construction reads only headers: it fails on missing shards, shards outside the folder, headers the
    safetensors library would refuse, truncated files and index entries that disagree with the shards, so
    that no work starts on a checkpoint that cannot be read to the end and nothing outside it is ever read.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        if self.path.is_dir():
            index = self.path / INDEX_NAME
            if os.path.lexists(index):
                self.files, self.specs, self.metadata = self._load_index(
                    _inside(self.path, INDEX_NAME, self.path, "index")
                )
            elif os.path.lexists(self.path / SINGLE_NAME):
                self.files = [_inside(self.path, SINGLE_NAME, self.path)]
                self.specs, self.metadata = _specs_of_file(self.files[0])
            else:
                raise CheckpointError(f"{self.path} has neither {INDEX_NAME} nor {SINGLE_NAME}")
        elif self.path.exists():
            self.files = [self.path]
            self.specs, self.metadata = _specs_of_file(self.path)
        else:
            raise CheckpointError(f"no such checkpoint: {self.path}")

    def _load_index(self, index: Path):
        try:
            doc = json.loads(index.read_text())
            weight_map: dict[str, str] = doc["weight_map"]
        except UnicodeDecodeError:
            raise CheckpointError(f"unreadable index {index}: not UTF-8") from None
        except (json.JSONDecodeError, RecursionError, KeyError, TypeError) as e:
            raise CheckpointError(f"unreadable index {index}: {e!r}") from None
        if not isinstance(weight_map, dict) or not all(isinstance(v, str) for v in weight_map.values()):
            raise CheckpointError(
                f"unreadable index {index}: weight_map must map tensor names to shard names"
            )
        if not isinstance(doc.get("metadata") or {}, dict):
            raise CheckpointError(f"unreadable index {index}: metadata is not an object")
        paths = {s: _inside(self.path, s, index) for s in dict.fromkeys(weight_map.values())}
        missing = [s for s, p in paths.items() if not p.exists()]
        if missing:
            raise CheckpointError(f"{index} names missing shard(s): {', '.join(missing)}")
        for s, p in paths.items():
            if not p.is_file():
                raise CheckpointError(f"{index}: shard {s!r} is not a regular file")
        shards = list(dict.fromkeys(paths.values()))  # "x" and "./x" are one file
        by_shard = {f: _specs_of_file(f) for f in shards}
        specs: dict[str, TensorSpec] = {}
        absent = []
        for name, shard in weight_map.items():
            spec = by_shard[paths[shard]][0].get(name)
            if spec is None:
                absent.append(name)
            else:
                specs[name] = spec
        if absent:
            raise CheckpointError(
                f"{len(absent)} tensor(s) in {index} are not in their shard: {_few(absent)}"
            )
        ordered = {k: specs[k] for k in sorted(specs, key=lambda k: (str(specs[k].file), specs[k].begin))}
        meta = dict(by_shard[shards[0]][1]) if shards else {}
        meta.update({k: str(v) for k, v in (doc.get("metadata") or {}).items() if k != "total_size"})
        return shards, ordered, meta

    def keys(self) -> list[str]:
        """Tensor names in storage order (shard by shard, by offset): the order that reads sequentially."""
        return list(self.specs)

    def __contains__(self, name: str) -> bool:
        return name in self.specs

    def __len__(self) -> int:
        return len(self.specs)

    @property
    def nbytes(self) -> int:
        return sum(s.nbytes for s in self.specs.values())

    @property
    def largest_tensor_nbytes(self) -> int:
        return max((s.nbytes for s in self.specs.values()), default=0)

    def read_bytes(self, name: str, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Read bytes [start, stop) of one tensor into a fresh, owned uint8 array (no memory map stays)."""
        spec = self.specs[name]
        stop = spec.nbytes if stop is None else stop
        if not 0 <= start <= stop <= spec.nbytes:
            raise ValueError(f"bytes [{start}, {stop}) are not inside tensor {name!r} ({spec.nbytes} bytes)")
        buf = np.empty(stop - start, dtype=np.uint8)
        with open(spec.file, "rb", buffering=0) as f:
            f.seek(spec.begin + start)
            view = memoryview(buf)
            got = 0
            while got < len(buf):
                n = f.readinto(view[got:])
                if not n:
                    raise CheckpointError(f"{spec.file} ended while reading tensor {name!r}")
                got += n
        return buf

    def read_raw(self, name: str, start: int = 0, stop: int | None = None) -> torch.Tensor:
        """`read_bytes` as a torch uint8 tensor (sharing its memory)."""
        import torch

        buf = self.read_bytes(name, start, stop)
        return torch.from_numpy(buf) if buf.size else torch.empty(0, dtype=torch.uint8)  # numpy: stride 0

    def chunk_bounds(self, name: str, chunk_bytes: int) -> list[tuple[int, int]]:
        """Byte ranges covering one tensor, each a whole number of elements and at most ~chunk_bytes."""
        spec = self.specs[name]
        item = spec.itemsize
        step = max(item, chunk_bytes // item * item)
        return [(b, min(b + step, spec.nbytes)) for b in range(0, spec.nbytes, step)] or [(0, 0)]

    def typed(self, name: str, raw: torch.Tensor) -> torch.Tensor:
        """View bytes from `read_raw` as the tensor they encode."""
        spec = self.specs[name]
        return raw.view(spec.torch_dtype).reshape(spec.shape)

    def get(self, name: str) -> torch.Tensor:
        return self.typed(name, self.read_raw(name))

    def items(self) -> Iterator[tuple[str, torch.Tensor]]:
        for name in self.specs:
            yield name, self.get(name)

    def sha256(self, file_hashes: Mapping[Path, str] | None = None) -> str:
        """Content hash: the file's sha256; for a sharded directory, the sha256 of `{shard: sha256}` JSON.

        `file_hashes` supplies per-file digests already computed elsewhere (e.g. while streaming).
        """
        hashes = {f: (file_hashes or {}).get(f) or file_sha256(f) for f in self.files}
        if len(self.files) == 1 and not (self.path / INDEX_NAME).exists():
            return hashes[self.files[0]]
        # shards by their path inside the folder (the base name alone would merge x/a and y/a)
        doc = json.dumps({f.relative_to(self.path).as_posix(): h for f, h in hashes.items()}, sort_keys=True)
        return hashlib.sha256(doc.encode()).hexdigest()

    def content_sha256(self, chunk: int = 8 << 20) -> str:
        """Hash of the tensors themselves, not of how they are stored: sha256 of the JSON
        `{name: [dtype, shape, sha256 of its bytes]}` (names sorted). The same weights as one file, as a
        folder or in other shards, with other metadata, have the same content hash."""
        doc = {}
        buf = np.empty(chunk, np.uint8)
        for name in sorted(self.specs):
            spec, h = self.specs[name], hashlib.sha256()
            with open(spec.file, "rb", buffering=0) as f:
                for b in range(spec.begin, spec.end, chunk):
                    n = min(chunk, spec.end - b)
                    f.seek(b)
                    view, got = memoryview(buf)[:n], 0
                    while got < n:
                        k = f.readinto(view[got:])
                        if not k:
                            raise CheckpointError(f"{spec.file} ended while reading tensor {name!r}")
                        got += k
                    h.update(view)
            doc[name] = [spec.dtype, list(spec.shape), h.hexdigest()]
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()

    def rename(self, strip_prefix: str | None = None, add_prefix: str | None = None, role: str = "") -> None:
        """Map tensor names (in place): `strip_prefix` taken off the names that start with it (some must),
        then `add_prefix` put in front of every name. For checkpoints whose keys differ by a wrapper
        prefix (`model.enc.weight` vs `enc.weight`); reading is unaffected."""
        what = f" of {role}" if role else ""
        specs = self.specs
        if strip_prefix:
            if not any(n.startswith(strip_prefix) for n in specs):
                raise CheckpointError(f"--strip-prefix {strip_prefix!r} begins no tensor name{what}")
            specs = {
                (n[len(strip_prefix) :] if n.startswith(strip_prefix) else n): s for n, s in specs.items()
            }
        if add_prefix:
            specs = {add_prefix + n: s for n, s in specs.items()}
        if len(specs) != len(self.specs):
            raise CheckpointError(
                f"--strip-prefix {strip_prefix!r} gives two tensors{what} the same name: "
                "a name with the prefix and one without it"
            )
        self.specs = specs


def file_sha256(path: str | os.PathLike, chunk: int = 8 << 20) -> str:
    h = hashlib.sha256()
    buf = bytearray(chunk)
    view = memoryview(buf)
    with open(path, "rb", buffering=0) as f:
        while n := f.readinto(buf):
            h.update(view[:n])
    return h.hexdigest()


def _few(names: list[str], k: int = 5) -> str:
    shown = ", ".join(repr(n) for n in names[:k])
    return shown + (f" (+{len(names) - k} more)" if len(names) > k else "")


def _fresh(out: Path, create) -> Path:
    """A new temporary name beside `out`, created by `create(path)`. Unlike mkstemp/mkdtemp (0600/0700)
    it gets the permissions the umask gives, which it keeps once renamed to `out` or into a store."""
    while True:
        tmp = out.parent / f".{out.name}.tmp-{secrets.token_hex(6)}"
        try:
            create(tmp)
            return tmp
        except FileExistsError:
            continue


def _new_file(path: Path) -> None:
    os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))


@contextlib.contextmanager
def atomic_directory(out: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary directory next to `out`; on success it is fsynced and renamed to `out`.

    On any exception the temporary directory is removed and `out` is left as it was.
    """
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists (pass overwrite=True to replace it)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = _fresh(out, os.mkdir)
    try:
        yield tmp
        fsync_files(tmp)
        old = None
        if out.exists():
            old = out.parent / f".{out.name}.old-{os.getpid()}"
            os.replace(out, old)
        os.replace(tmp, out)
        fsync_dir(out.parent)
        if old is not None:
            shutil.rmtree(old) if old.is_dir() else old.unlink()
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@functools.cache
def _sync_file_range():
    try:
        import ctypes

        fn = ctypes.CDLL(None, use_errno=True).sync_file_range
    except (OSError, AttributeError):  # not Linux
        return None
    fn.argtypes = (ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint)
    return fn


def start_writeback(fd: int, begin: int, end: int) -> None:
    """Queue bytes [begin, end) (`end` 0: the whole file) for writing to disk without waiting (Linux's
    sync_file_range), so that they are written while the rest is computed and the fsync at close finds
    little left to do."""
    fn = _sync_file_range()
    if fn is not None:
        fn(fd, begin, end - begin, 2)  # SYNC_FILE_RANGE_WRITE


def _known_dtype(dtype: object) -> str:
    name = dtype_name(dtype)
    if name is None:
        raise CheckpointError(f"dtype {dtype} cannot be stored in safetensors")
    return name


def _torch_uint8():
    import torch

    return torch.uint8


def _header_bytes(entries: list[tuple[str, str, tuple[int, ...], int, int]], metadata: Mapping[str, str]):
    header: dict = {"__metadata__": dict(metadata)} if metadata else {}
    for name, dtype, shape, b, e in entries:
        header[name] = {"dtype": dtype, "shape": list(shape), "data_offsets": [b, e]}
    raw = json.dumps(header, separators=(",", ":")).encode()
    return raw + b" " * (-len(raw) % 8)  # pad so tensor data starts 8-byte aligned


def _plan_shards(sizes: Mapping[str, int], max_shard_bytes: int) -> tuple[list[list[str]], list[str]]:
    """Tensor names per shard and the shards' file names, as Hugging Face plans them
    (`split_state_dict_into_shards_factory`: the same grouping, file names and single-shard
    `model.safetensors` as `save_torch_state_dict`, which we cannot call itself: it needs every tensor
    in memory at once, and we write each one as it is computed). The plan needs only the sizes.
    Tensors keep their order; one larger than a shard gets a shard of its own."""
    from huggingface_hub import split_state_dict_into_shards_factory

    split = split_state_dict_into_shards_factory(
        dict(sizes),
        get_storage_size=lambda size: size,
        filename_pattern="model{suffix}.safetensors",
        max_shard_size=max_shard_bytes,
        get_storage_id=lambda size: None,  # every tensor has storage of its own
    )
    if not sizes:  # nothing to split: one empty shard, as before
        return [[]], [SINGLE_NAME]
    names = list(split.filename_to_tensors)
    return [split.filename_to_tensors[n] for n in names], names


def parse_size(text: str | int) -> int:
    """A shard size: bytes, or a number with KB/MB/GB/TB (powers of 1000, as Hugging Face reads them)
    or KiB/MiB/GiB/TiB (powers of 1024)."""
    if isinstance(text, int):
        value = text
    else:
        s = str(text).strip().upper().replace(" ", "")
        units = {"KIB": 1 << 10, "MIB": 1 << 20, "GIB": 1 << 30, "TIB": 1 << 40}
        units |= {"KB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12, "B": 1, "": 1}
        unit = next(u for u in sorted(units, key=len, reverse=True) if s.endswith(u))
        try:
            value = int(float(s[: len(s) - len(unit)]) * units[unit])
        except ValueError:
            raise ValueError(f"not a size: {text!r} (e.g. 5GB, 500MiB, 1000000)") from None
    if value <= 0:
        raise ValueError(f"a shard size must be positive, got {text!r}")
    return value


class ShardedWriter:
    """Write tensors one at a time into a safetensors file or a sharded directory, atomically.

    `specs` fixes the names (in write order), dtypes and shapes, so every header is known before any data.
    `out` ending in `.safetensors` gives one file; anything else gives a directory: `model.safetensors`
    when everything fits into one shard, else `model-0000i-of-0000n.safetensors` shards and
    `model.safetensors.index.json`.
    Metadata values whose final text is only known at the end (e.g. input hashes computed while reading)
    can be changed with `set_metadata` before closing, as long as they keep their byte length.
    Use as a context manager; nothing becomes visible under `out` unless the block completes.
    """

    def __init__(
        self,
        out: str | os.PathLike,
        specs: Mapping[str, tuple[torch.dtype | str, tuple[int, ...]]],
        metadata: Mapping[str, str] | None = None,
        max_shard_bytes: int = DEFAULT_MAX_SHARD_BYTES,
        overwrite: bool = False,
    ):
        self.out = Path(out)
        self.metadata = dict(metadata or {})
        self.overwrite = overwrite
        self.single_file = self.out.suffix == ".safetensors"
        self._specs = {n: (_known_dtype(d), tuple(s)) for n, (d, s) in specs.items()}
        sizes = {n: math.prod(s) * STORAGE[d].itemsize for n, (d, s) in self._specs.items()}
        if self.single_file:
            shards, self.shard_names = [list(specs)], [self.out.name]
        else:
            shards, self.shard_names = _plan_shards(sizes, max_shard_bytes)
        self._shards = shards
        self._sizes = sizes
        self._order = [name for shard in shards for name in shard]
        self._pos = 0
        self._ctx = None
        self._files: list = []
        self._header_len: list[int] = []
        self._queued: dict = {}  # file -> offset up to which its writeback was started
        self._extra: dict[str, bytes | Path] = {}  # other files of a folder output (`add_file`)

    @property
    def order(self) -> list[str]:
        return list(self._order)

    def _entries(self, shard: list[str]):
        off = 0
        for name in shard:
            dtype, shape = self._specs[name]
            yield name, dtype, shape, off, off + self._sizes[name]
            off += self._sizes[name]

    def __enter__(self) -> ShardedWriter:
        if self.single_file:
            if self.out.exists() and not self.overwrite:
                raise FileExistsError(f"{self.out} exists (pass overwrite=True to replace it)")
            self.out.parent.mkdir(parents=True, exist_ok=True)
            self._dir = None
            paths = [_fresh(self.out, _new_file)]
        else:
            self._ctx = atomic_directory(self.out, self.overwrite)
            self._dir = self._ctx.__enter__()
            paths = [self._dir / s for s in self.shard_names]
        self._paths = paths
        try:
            for path, shard in zip(paths, self._shards, strict=True):
                f = open(path, "wb")
                self._files.append(f)
                head = _header_bytes(list(self._entries(shard)), self.metadata)
                self._header_len.append(len(head))
                f.write(struct.pack("<Q", len(head)))
                f.write(head)
        except BaseException:
            self._abort()
            raise
        self._shard_of = {name: i for i, shard in enumerate(self._shards) for name in shard}
        return self

    def _expect(self, name: str) -> None:
        expected = self._order[self._pos] if self._pos < len(self._order) else None
        if name != expected:
            raise CheckpointError(f"writer expected tensor {expected!r} next, got {name!r}")

    def write(self, name: str, tensor: torch.Tensor) -> None:
        """Append the next tensor; it must be the next name of `order`, with the declared dtype and shape."""
        self._expect(name)
        dtype, shape = self._specs[name]
        if dtype_name(tensor.dtype) != dtype or tuple(tensor.shape) != shape:
            raise CheckpointError(
                f"tensor {name!r}: got {tensor.dtype} {tuple(tensor.shape)}, declared {dtype} {shape}"
            )
        self.write_chunks(name, [tensor])

    def write_chunks(self, name: str, chunks) -> None:
        """Append the next tensor from pieces (flat, in order) that add up to its size: torch tensors of
        its dtype, or numpy arrays of its `STORAGE` dtype."""
        self._expect(name)
        dtype = self._specs[name][0]
        f = self._files[self._shard_of[name]]
        written = 0
        for chunk in chunks:
            if isinstance(chunk, np.ndarray):
                if chunk.dtype != STORAGE[dtype]:
                    raise CheckpointError(f"tensor {name!r}: got {chunk.dtype}, declared {dtype}")
                raw = np.ascontiguousarray(chunk).reshape(-1).view(np.uint8)
            else:
                if dtype_name(chunk.dtype) != dtype:
                    raise CheckpointError(f"tensor {name!r}: got {chunk.dtype}, declared {dtype}")
                raw = chunk.detach().to("cpu").contiguous().reshape(-1).view(_torch_uint8()).numpy()
            written += f.write(memoryview(raw))
            if f.tell() - self._queued.get(f, 0) >= WRITEBACK_BYTES:
                f.flush()
                start_writeback(f.fileno(), self._queued.get(f, 0), f.tell())
                self._queued[f] = f.tell()
        if written != self._sizes[name]:
            raise CheckpointError(f"tensor {name!r}: wrote {written} bytes, declared {self._sizes[name]}")
        self._pos += 1

    def add_file(self, name: str, content: bytes | str | os.PathLike) -> None:
        """Put another file (bytes, or a file's path to copy) into a folder output, at `name` (relative,
        `/`-separated); written when the writer closes, inside the same atomic rename as the shards."""
        if self.single_file:
            raise CheckpointError(f"{self.out} is one .safetensors file: it cannot hold {name!r} beside it")
        parts = Path(name).parts
        if not parts or Path(name).is_absolute() or ".." in parts:
            raise CheckpointError(f"{name!r} is not a relative file name inside the output folder")
        if name in self.shard_names or name == INDEX_NAME:
            raise CheckpointError(f"{name!r} would replace a weight file of the output")
        self._extra[name] = (
            content
            if isinstance(content, bytes)
            else (content.encode() if isinstance(content, str) else Path(content))
        )

    def set_metadata(self, key: str, value: str) -> None:
        """Replace a metadata value by one of the same encoded length (rewritten in place at close)."""
        old = self.metadata.get(key)
        if old is None or len(json.dumps(old)) != len(json.dumps(value)):
            raise ValueError(f"metadata {key!r} must exist and keep its length to be set late")
        self.metadata[key] = value

    def _abort(self) -> None:
        for f in self._files:
            f.close()
        if self._ctx is not None:
            with contextlib.suppress(BaseException):
                self._ctx.__exit__(RuntimeError, RuntimeError("aborted"), None)
        else:
            for p in self._paths:
                p.unlink(missing_ok=True)

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is not None:
            self._abort()
            return False
        if self._pos != len(self._order):
            self._abort()
            raise CheckpointError(f"writer closed after {self._pos} of {len(self._order)} tensors")
        try:
            self._finish()
        except BaseException:
            self._abort()
            raise
        return False

    def _finish(self) -> None:
        for f, shard, n in zip(self._files, self._shards, self._header_len, strict=True):
            head = _header_bytes(list(self._entries(shard)), self.metadata)
            assert len(head) == n
            f.seek(8)
            f.write(head)
            f.flush()
            os.fsync(f.fileno())
            f.close()
        if self.single_file:
            os.replace(self._paths[0], self.out)
            fsync_dir(self.out.parent)
            return
        if len(self._shards) > 1:
            index = {
                "metadata": {"total_size": sum(self._sizes.values()), **self.metadata},
                "weight_map": {name: self.shard_names[i] for name, i in self._shard_of.items()},
            }
            (self._dir / INDEX_NAME).write_text(json.dumps(index, indent=2))
        for name, content in self._extra.items():
            dst = self._dir / name
            dst.parent.mkdir(parents=True, exist_ok=True)
            if isinstance(content, bytes):
                dst.write_bytes(content)
            else:
                shutil.copyfile(content, dst)  # the content, links followed
        self._ctx.__exit__(None, None, None)


def write_checkpoint(
    out: str | os.PathLike,
    tensors: Mapping[str, torch.Tensor],
    metadata: Mapping[str, str] | None = None,
    max_shard_bytes: int = DEFAULT_MAX_SHARD_BYTES,
    overwrite: bool = False,
) -> None:
    """Write an in-memory dict with the same layout and atomicity as `ShardedWriter` (small checkpoints)."""
    specs = {n: (t.dtype, tuple(t.shape)) for n, t in tensors.items()}
    with ShardedWriter(out, specs, metadata, max_shard_bytes, overwrite) as w:
        for name in w.order:
            w.write(name, tensors[name])
