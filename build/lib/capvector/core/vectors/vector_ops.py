"""Streaming capability-vector arithmetic on safetensors checkpoints: `extract`, `merge`, `mean`, `stats`.

All of them walk the checkpoints tensor by tensor, each tensor in pieces of `CHUNK_BYTES` (memory bounded
by a few pieces, whatever the tensors' size), so they work on any safetensors checkpoint, including a
sharded Hugging Face one. Conventions:
- float16/bfloat16 are computed in float32 and written back in their own dtype (float64 stays float64),
  rounded to nearest even; a merge term α·vector is rounded before it is added (as `base + α * vector`
  is in torch or numpy);
- the arithmetic is numpy's on the stored bytes (bfloat16 by its bits): torch is not imported, which
  would take a CLI command longer than streaming a 256 MiB checkpoint;
- non-float tensors (step counters, index buffers) are carried over when equal in every input, refused
  otherwise;
- every structural check (keys, shapes, dtypes, filters) runs before anything is written; value checks
  (NaN/Inf, overflow on the cast back, wrong base) run while streaming into a temporary name that is
  removed on failure, so a failed call never leaves an output behind;
- outputs carry metadata: `capvector.kind`, `capvector.formula`, `capvector.coefficients`,
  `capvector.inputs` (role -> sha256, hashed from the bytes read, in a helper thread; never a path,
  so the same inputs give the same bytes wherever they are stored, and hence the same artifact id),
  `capvector.include`/`capvector.exclude`, and for vectors `capvector.partial` and optionally
  `capvector.base_sha256` (the θ_pt the vector is meant to be added to); a merge also keeps base's
  metadata (its policy config: a merged policy loads like its base; see `merge`); a mean says its
  `capvector.method` (and `capvector.density` for TIES).

Name filters: `include`/`exclude` are lists of patterns in the project's one syntax
(`capvector.core.vectors.module_patterns`, shared with LoRA targets): a shell-style glob on the whole name
(`*` also crosses dots: `backbone.*`) or on its trailing dotted components (`attn.*_proj.weight`), or,
prefixed with `re:`, a Python regular expression that must match the whole name (`re:blocks\\.[0-3]\\..*`). A
tensor is selected when it matches some include pattern (or there is none) and no exclude pattern. A pattern
that matches no tensor at all, or a selection that is empty, is an error (it is almost always a typo).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import math
import os
import re
from collections.abc import Iterable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from decimal import Decimal
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel

from capvector.core.vectors import model_card, module_patterns
from capvector.core.vectors.safetensors_io import (
    DEFAULT_MAX_SHARD_BYTES,
    FLOATS,
    STORAGE,
    WRITEBACK_BYTES,
    Checkpoint,
    CheckpointError,
    ShardedWriter,
    TensorSpec,
    _few,
    start_writeback,
    torch_dtype,
)

PathLike = str | os.PathLike
_PLACEHOLDER = "0" * 64
CHUNK_BYTES = 4 << 20  # tensors are processed in pieces of this size: memory does not grow with them
# Base metadata a merge carries (besides base's non-`capvector.` keys): the policy config, so a merged
# policy checkpoint loads like its base. Equal to `capvector.core.policies.base.CONFIG_METADATA_KEY` (tested).
CARRIED_KEYS = ("capvector.policy_config",)


class VectorOpError(CheckpointError):
    """Inputs that cannot be combined (mismatch, non-finite values, wrong base, bad filter)."""


def select_names(
    names: Iterable[str], include: Sequence[str] | None = None, exclude: Sequence[str] | None = None
) -> list[str]:
    """Apply include/exclude patterns (`module_patterns` syntax); errors on patterns that match nothing."""
    try:
        return module_patterns.select(names, include, exclude, what="tensor")
    except module_patterns.PatternError as e:
        raise VectorOpError(str(e)) from None


def _is_float(spec: TensorSpec) -> bool:
    return spec.is_float


def _compare(
    ref: Checkpoint, other: Checkpoint, role: str, names: Iterable[str], compute: str | None = None
) -> None:
    """Shapes and dtypes of `names` must agree (float dtypes may differ given a compute dtype); raise
    naming a few offending tensors, the count, and the flag that would accept them."""
    bad, floats_only = [], True
    for n in names:
        a, b = ref.specs[n], other.specs[n]
        mixed_floats = a.dtype != b.dtype and a.is_float and b.is_float
        if a.shape != b.shape or (a.dtype != b.dtype and not (mixed_floats and compute)):
            bad.append(f"{n} ({a.dtype}{list(a.shape)} vs {b.dtype}{list(b.shape)})")
            floats_only &= a.shape == b.shape and mixed_floats
    if bad:
        hint = (
            "; pass --dtype float32 to compute floats of different dtypes in float32 (and --out-dtype to "
            "choose the output's)"
            if floats_only
            else ""
        )
        raise VectorOpError(
            f"{len(bad)} tensor(s) of {role} differ in shape or dtype: {', '.join(bad[:5])}{hint}"
        )


COMPUTE_DTYPES = {"float32": np.float32, "float64": np.float64}
_DTYPE_NAMES = {
    "float32": "F32", "fp32": "F32", "f32": "F32",
    "float64": "F64", "fp64": "F64", "f64": "F64", "double": "F64",
    "float16": "F16", "fp16": "F16", "f16": "F16", "half": "F16",
    "bfloat16": "BF16", "bf16": "BF16",
}  # fmt: skip


def float_dtype(name: str | None, flag: str = "--out-dtype") -> str | None:
    """A float dtype as safetensors spells it (`F32`), from `float32`, `fp32`, `bf16`, `F32`, ..."""
    if name is None:
        return None
    key = str(name).strip()
    found = _DTYPE_NAMES.get(key.lower()) or (key.upper() if key.upper() in FLOATS else None)
    if found is None:
        raise VectorOpError(f"{flag} {name!r}: not a float dtype (float32, float64, float16, bfloat16)")
    return found


def compute_dtype(name: str | None) -> str | None:
    """The `--dtype` arithmetic is done in: float32 or float64 (None: float32, float64 for F64)."""
    found = float_dtype(name, "--dtype")
    if found not in (None, "F32", "F64"):
        raise VectorOpError(
            f"--dtype {name!r}: compute in float32 or float64 (--out-dtype sets the output's)"
        )
    return {None: None, "F32": "float32", "F64": "float64"}[found]


def _wide_for(compute: str | None, *dtypes: str) -> type:
    """The numpy type a tensor is computed in: `compute` if given, else float64 if an input is F64."""
    if compute is not None:
        return COMPUTE_DTYPES[compute]
    return np.float64 if "F64" in dtypes else np.float32


def _to(x: np.ndarray, dtype: str, wide: type, scratch: _Scratch, key: str) -> np.ndarray:
    """Stored values of `dtype` as `wide` (x itself when it already is; else into scratch[key])."""
    w = x if dtype in ("F32", "F64") else _widen(x, dtype, scratch(key, x.size, np.float32))
    if w.dtype == wide:
        return w
    out = scratch(key + ".wide", x.size, wide)
    np.copyto(out, w, casting="same_kind")
    return out


def _byte_bounds(ckpts: Sequence[Checkpoint], name: str) -> list[list[tuple[int, int]]]:
    """Per checkpoint, byte ranges covering tensor `name` that hold the same elements in each (their
    dtypes may differ), each at most ~CHUNK_BYTES in the widest."""
    specs = [c.specs[name] for c in ckpts]
    item = max(s.itemsize for s in specs)
    numel = specs[0].nbytes // specs[0].itemsize
    step = max(1, CHUNK_BYTES // item)
    elements = [(b, min(b + step, numel)) for b in range(0, numel, step)] or [(0, 0)]
    return [[(b * s.itemsize, e * s.itemsize) for b, e in elements] for s in specs]


def _key_diff(ref: Checkpoint, other: Checkpoint, role: str, allow_missing: bool = False) -> None:
    extra = [k for k in other.keys() if k not in ref]
    missing = [] if allow_missing else [k for k in ref.keys() if k not in other]
    msgs = []
    if missing:
        msgs.append(f"{len(missing)} tensor(s) missing from {role}: {_few(missing)}")
    if extra:
        msgs.append(f"{len(extra)} unexpected tensor(s) in {role}: {_few(extra)}")
    if msgs:
        prefixes = " (names that differ by a prefix: --strip-prefix / --add-prefix)" if extra else ""
        raise VectorOpError("; ".join(msgs) + prefixes)


class _HashingReader:
    """Reads tensors of one checkpoint and hashes its files from those same bytes, in a helper thread.

    Tensors read in storage order feed the running sha256 of their file; anything out of order (or not
    read at all) is hashed from disk at the end, so the digest is always the file's true sha256. A file
    replaced or written to while it is read (its inode, size, mtime or ctime moved) is refused: its
    digest would name bytes other than those computed from. With `copies` (file -> new path), a file is
    read through a `_Copy` at that path: a private copy of exactly the bytes hashed and computed from,
    made while the computation runs rather than before it (a file is copied by the first reader that
    claims it: its entry is taken out of `copies`).
    """

    def __init__(self, ckpt: Checkpoint, pool: ThreadPoolExecutor, copies: Mapping[Path, Path] | None = None):
        self.ckpt = ckpt
        self.pool = pool
        self.state: dict[Path, list] = {}
        self.stats: dict[Path, tuple[int, ...]] = {}
        self.copies: dict[Path, _Copy] = {}
        self.pending: Future | None = None
        self.pending_turn = 0
        self.ring: list[np.ndarray | None] = [None, None]  # read buffers, reused (see `_buffer`)
        self.turn = 0
        self.done: dict[Path, str] | None = None
        for f in ckpt.files:
            self.stats[f] = _identity(f.stat())
            if copies and f in copies:
                self.copies[f] = _Copy(f, copies.pop(f))
            h, first = hashlib.sha256(), _read(f, self.copies.get(f), 0, np.empty(8, np.uint8))
            h.update(memoryview(first))
            end = 8 + int.from_bytes(first.tobytes(), "little")  # the header: 8 bytes, then its JSON
            _hash_range(h, f, 8, end, self.copies.get(f))
            self.state[f] = [h, end]

    def chunks(self, name: str, bounds: list[tuple[int, int]]) -> Iterator[np.ndarray]:
        """Flat pieces of one tensor (its `STORAGE` dtype), read (and hashed) in the byte ranges `bounds`."""
        spec = self.ckpt.specs[name]
        copy = self.copies.get(spec.file)
        for b, e in bounds:
            raw = _read(spec.file, copy, spec.begin + b, self._buffer(e - b)[: e - b])
            st = self.state[spec.file]
            if st[1] is not None and st[1] <= spec.begin + b:
                self._wait()
                if st[1] < spec.begin + b:  # bytes skipped (tensors not needed, padding): hash from disk
                    _hash_range(st[0], spec.file, st[1], spec.begin + b, copy)
                self.pending, self.pending_turn = self.pool.submit(st[0].update, memoryview(raw)), self.turn
                st[1] = spec.begin + e
            else:
                st[1] = None  # read out of order: hash the whole file (its copy) from disk at the end
            yield raw.view(STORAGE[spec.dtype])

    def _buffer(self, n: int) -> np.ndarray:
        """The two read buffers in turn: the other one holds the chunk just handed out, which may still
        be being hashed. The consumer is done with a chunk when it asks for the next but one (it writes
        each result before asking again), and a buffer still being hashed is waited for. Fresh
        multi-MiB arrays would each be page-faulted and zeroed by the kernel."""
        self.turn ^= 1
        if self.pending_turn == self.turn:
            self._wait()
        buf = self.ring[self.turn]
        if buf is None or buf.size < n:
            buf = self.ring[self.turn] = np.empty(max(n, CHUNK_BYTES), np.uint8)
        return buf

    def _wait(self) -> None:
        if self.pending is not None:
            self.pending.result()
            self.pending = None

    def file_digests(self) -> dict[Path, str]:
        """sha256 of each file (of the bytes read; the rest hashed, and copied, from disk now)."""
        if self.done is not None:
            return self.done
        self._wait()
        done = {}
        for f, (h, pos) in self.state.items():
            if pos is None:
                h, pos = hashlib.sha256(), 0
            _hash_range(h, f, pos, self.stats[f][2], self.copies.get(f))
            done[f] = h.hexdigest()
            if _identity(f.stat()) != self.stats[f]:
                raise VectorOpError(f"{f} changed while it was being read; run the command again")
        self.close()
        self.done = done
        return done

    def peek(self, name: str, bounds: list[tuple[int, int]], buf: np.ndarray) -> Iterator[np.ndarray]:
        """The pieces of `chunks`, read into `buf` (through the file's copy, if it has one) but not
        hashed: a pass that only looks ahead (`mean`'s TIES threshold). `chunks` reads them again
        afterwards, and hashes what it computes from; a file changed in between is refused by
        `file_digests` (its identity) or by the caller's check of the digest."""
        spec = self.ckpt.specs[name]
        copy = self.copies.get(spec.file)
        for b, e in bounds:
            yield _read(spec.file, copy, spec.begin + b, buf[: e - b]).view(STORAGE[spec.dtype])

    def copied(self) -> dict[Path, str]:
        """copy path -> sha256 of its bytes (those hashed and computed from)."""
        digests = self.file_digests()
        return {copy.path: digests[f] for f, copy in self.copies.items()}

    def close(self) -> None:
        self._wait()
        for copy in self.copies.values():
            copy.close()

    def sha256(self) -> str:
        return self.ckpt.sha256(self.file_digests())


class _Copy:
    """A private copy of a file, filled range by range just before each range is read, then read from
    there: what is hashed and computed from is exactly what is stored, whatever the source does
    meanwhile. The kernel copies (copy_file_range: page cache to page cache, half the cost of a write
    from user space); across filesystems, where it cannot, the bytes are read from the source and
    written to the copy. Writeback is started as the copy grows (the fsync before its commit then finds
    little left to do)."""

    def __init__(self, src: Path, path: Path):
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self.src = os.open(src, os.O_RDONLY)
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)
        self.kernel = True
        self.filled: list[tuple[int, int]] = []  # copied ranges, sorted and disjoint
        self.unqueued = 0

    def read(self, begin: int, out: np.ndarray) -> np.ndarray:
        """Bytes [begin, begin + out.size) of the copy into `out`, copied from the source if new."""
        for start, end in self._missing(begin, begin + out.size):
            b = start
            if self.kernel:
                try:
                    while b < end:
                        n = os.copy_file_range(self.src, self.fd, end - b, b, b)
                        if not n:
                            raise CheckpointError(f"{self.path.name}: the source ended at byte {b}")
                        b += n
                except OSError:
                    self.kernel = False  # another filesystem, an old kernel: through user space
            if b < end:
                view = memoryview(_pread(self.src, out[b - begin : end - begin], b))
                while view:
                    n = os.pwrite(self.fd, view, b)
                    view, b = view[n:], b + n
            self._mark(start, end)
        return _pread(self.fd, out, begin)

    def _missing(self, begin: int, end: int) -> list[tuple[int, int]]:
        gaps = []
        for b, e in self.filled:
            if b > begin:
                gaps.append((begin, min(b, end)))
            begin = max(begin, e)
            if begin >= end:
                break
        if begin < end:
            gaps.append((begin, end))
        return [(b, e) for b, e in gaps if b < e]

    def _mark(self, begin: int, end: int) -> None:
        spans = sorted([*self.filled, (begin, end)])
        self.filled = [spans[0]]
        for b, e in spans[1:]:
            if b <= self.filled[-1][1]:
                self.filled[-1] = (self.filled[-1][0], max(e, self.filled[-1][1]))
            else:
                self.filled.append((b, e))
        self.unqueued += end - begin
        if self.unqueued >= WRITEBACK_BYTES:
            start_writeback(self.fd, 0, 0)  # all of it so far
            self.unqueued = 0

    def close(self) -> None:
        for fd in (self.src, self.fd):
            with contextlib.suppress(OSError):
                os.close(fd)


def _pread(fd: int, out: np.ndarray, offset: int) -> np.ndarray:
    view, got = memoryview(out).cast("B"), 0
    while got < len(view):
        n = os.preadv(fd, [view[got:]], offset + got)
        if not n:
            raise CheckpointError(f"a file ended at byte {offset + got}, before the data it must hold")
        got += n
    return out


def _read(path: Path, copy: _Copy | None, offset: int, out: np.ndarray) -> np.ndarray:
    """Bytes at `offset` of a file (through its copy, if it has one) into `out`."""
    if copy is not None:
        return copy.read(offset, out)
    with open(path, "rb", buffering=0) as f:
        return _pread(f.fileno(), out, offset)


def _identity(st: os.stat_result) -> tuple[int, ...]:
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def _hash_range(h, path: Path, begin: int, end: int, copy: _Copy | None = None, chunk: int = 8 << 20) -> None:
    """Hash bytes [begin, end) of a file (through its copy, if it has one)."""
    buf = np.empty(min(chunk, max(end - begin, 0)), np.uint8)
    while begin < end:
        n = min(chunk, end - begin)
        h.update(memoryview(_read(path, copy, begin, buf[:n])))
        begin += n


class _Scratch:
    """Work arrays reused from chunk to chunk (each result is written before the next chunk is
    computed): fresh multi-MiB arrays would each be page-faulted and zeroed by the kernel."""

    def __init__(self) -> None:
        self.bufs: dict[str, np.ndarray] = {}

    def __call__(self, key: str, n: int, dtype: type | np.dtype) -> np.ndarray:
        need = n * np.dtype(dtype).itemsize
        buf = self.bufs.get(key)
        if buf is None or buf.size < need:
            buf = self.bufs[key] = np.empty(need, np.uint8)
        return buf[:need].view(dtype)


def _wide(dtype: str) -> type:
    """The dtype a stored dtype is computed in."""
    return np.float64 if dtype == "F64" else np.float32


def _widen(x: np.ndarray, dtype: str, out: np.ndarray | None = None) -> np.ndarray:
    """Stored values as float32 (float64 for F64) to compute with: F32/F64 as they are, else converted
    (into `out` when given)."""
    if dtype in ("F32", "F64"):
        return x
    if dtype == "F16":
        if out is None:
            return x.astype(np.float32)
        np.copyto(out, x)
        return out
    if dtype == "BF16":  # the 16 bits are the high half of a float32
        bits = None if out is None else out.view(np.uint32)
        return np.left_shift(x, 16, dtype=np.uint32, out=bits).view(np.float32)
    return _via_torch(x, dtype, "F32")


def _narrow(acc: np.ndarray, dtype: str, scratch: _Scratch | None = None) -> np.ndarray:
    """A float32/64 result as stored values of `dtype`, rounded to nearest even (as torch rounds; a
    float64 result goes to bfloat16 through float32)."""
    scratch = scratch or _Scratch()
    if dtype in ("F32", "F64"):
        if acc.dtype == STORAGE[dtype]:
            return acc
        out = scratch("narrow", acc.size, STORAGE[dtype])
        with np.errstate(over="ignore"):  # an overflow to Inf is refused by the caller, naming the tensor
            np.copyto(out, acc, casting="same_kind")
        return out
    if dtype == "BF16" and acc.dtype == np.float64:
        acc32 = scratch("narrow32", acc.size, np.float32)
        with np.errstate(over="ignore"):
            np.copyto(acc32, acc, casting="same_kind")
        acc = acc32
    out = scratch("narrow", acc.size, STORAGE[dtype])
    if dtype == "F16":
        with np.errstate(over="ignore"):  # an overflow to Inf is refused by the caller, naming the tensor
            np.copyto(out, acc, casting="same_kind")
        return out
    if dtype == "BF16":  # round the 16 dropped bits to nearest even (acc is finite: no NaN to keep)
        bits = acc.view(np.uint32)
        rounded = np.right_shift(bits, 16, out=scratch("round", acc.size, np.uint32))
        rounded &= 1
        rounded += 0x7FFF
        rounded += bits
        np.copyto(out, rounded.view(np.uint16)[1::2])  # the high halves (little-endian, as safetensors)
        return out
    return _via_torch(acc, "F32", dtype)


def _via_torch(x: np.ndarray, src: str, dst: str) -> np.ndarray:
    """float8 conversions, which numpy lacks (rare enough to pay torch's import)."""
    import torch

    out = torch.from_numpy(x).view(torch_dtype(src)).to(torch_dtype(dst))
    return out.view(torch.uint8).numpy() if STORAGE[dst] == np.uint8 else out.numpy()


def _all_finite(x: np.ndarray) -> bool:
    """No NaN or Inf in a float32/64 array. A sum is non-finite iff some element is (NaN/Inf propagate)
    or it overflows: far cheaper than isfinite().all(), which only then decides."""
    with np.errstate(over="ignore", invalid="ignore"):
        if math.isfinite(x.sum()):
            return True
    return bool(np.isfinite(x).all())


def _stored_finite(x: np.ndarray, dtype: str) -> bool:
    if dtype not in FLOATS:
        return True
    if dtype == "BF16":  # all exponent bits set (Inf, NaN): the magnitude bits reach 0x7F80
        return x.size == 0 or int((x & 0x7FFF).max()) < 0x7F80
    return _all_finite(_widen(x, dtype))


def _finite_or_raise(x: np.ndarray, dtype: str, name: str, role: str) -> None:
    if not _stored_finite(x, dtype):
        raise VectorOpError(f"NaN or Inf in tensor {name!r} of {role}")


def _cast_back(
    acc: np.ndarray,
    dtype: str,
    name: str,
    inputs: list[tuple[str, np.ndarray, str]],
    scratch: _Scratch | None = None,
) -> np.ndarray:
    """Round a float32/64 result to the output dtype; if it is not finite, name the input responsible.
    `inputs`: (role, stored values, their dtype)."""
    if _all_finite(acc):
        out = _narrow(acc, dtype, scratch)
        if out is acc or _stored_finite(out, dtype):
            return out
    for role, x, x_dtype in inputs:
        _finite_or_raise(x, x_dtype, name, role)
    raise VectorOpError(f"result for tensor {name!r} overflows {dtype}")


def _inputs_meta(readers: dict[str, _HashingReader]) -> dict[str, dict[str, str]]:
    """role -> {"sha256": ...}: content digests only. A path (a store's, a home's, a user's folder) would
    make the output's bytes, so its content id, depend on where the inputs happened to be read from."""
    return {role: {"sha256": _PLACEHOLDER} for role in readers}


class Card(BaseModel):
    """What a folder output's README.md card says besides the formula and the input hashes."""

    command: str  # the command, inputs by role (`{base}`, `{vector_0}`): replaced by their ids or hashes
    settings: dict[str, object] = {}
    alphas: dict[str, float] = {}  # role -> coefficient
    extra_inputs: dict[str, str] = {}  # role -> sha256 of inputs not streamed (extract's --base)


def _run(
    out: PathLike,
    names: list[str],
    ref: Checkpoint,
    readers: dict[str, _HashingReader],
    metadata: dict[str, str],
    compute,
    max_shard_bytes: int,
    overwrite: bool,
    check=None,
    hashes: dict[Path, str] | None = None,
    dtypes: Mapping[str, str] | None = None,
    carry_from: Path | None = None,
    card: Card | None = None,
    input_ids=None,
) -> Path:
    """Stream `compute(name) -> flat pieces` for every name into `out`, then fill in the input hashes.

    A folder output also gets the files of `carry_from` that are not weights (`model_card.companion_files`)
    and, with `card`, a README.md naming the inputs by `input_ids(role)` (artifact ids; None: unknown) and
    sha256. `dtypes`: output dtype per name (default: `ref`'s)."""
    inputs = _inputs_meta(readers)
    metadata = {**metadata, "capvector.inputs": json.dumps(inputs, sort_keys=True)}
    specs = {n: ((dtypes or {}).get(n, ref.specs[n].dtype), ref.specs[n].shape) for n in names}
    folder = Path(out).suffix != ".safetensors"
    carried = []
    if folder and carry_from is not None and carry_from.is_dir():
        # the weights by their names in `ref` (a copy of it being filled as it is read is no checkpoint yet)
        weights = [f.relative_to(ref.path).as_posix() for f in ref.files] if ref.path.is_dir() else None
        carried = model_card.companion_files(carry_from, weights)
    with ShardedWriter(out, specs, metadata, max_shard_bytes, overwrite) as w:
        for n in w.order:
            w.write_chunks(n, compute(n))
        digests = {role: r.sha256() for role, r in readers.items()}
        if check is not None:
            check(digests)
        for role, d in digests.items():
            inputs[role]["sha256"] = d
        w.set_metadata("capvector.inputs", json.dumps(inputs, sort_keys=True))
        if hashes is not None:
            for r in readers.values():
                _record(hashes, r.file_digests() | r.copied())
        for rel in carried:
            w.add_file(rel, carry_from / rel)
        if folder and card is not None:
            w.add_file(model_card.CARD_NAME, _card_text(metadata, digests, card, input_ids, carried))
    return Path(out)


def _fill(command: str, names: Mapping[str, str]) -> str:
    for role, name in names.items():
        command = command.replace("{" + role + "}", name)
    return command


def _card_text(metadata: dict[str, str], digests: dict[str, str], card: Card, input_ids, carried) -> str:
    rows, names = [], {}
    for role, sha in {**digests, **card.extra_inputs}.items():
        found = input_ids(role) if input_ids is not None else None
        rows.append({"role": role, "alpha": card.alphas.get(role), "id": found, "sha256": sha})
        names[role] = found or sha
    return model_card.render_card(
        metadata["capvector.kind"],
        metadata["capvector.formula"],
        rows,
        _fill(card.command, names),
        card.settings,
        carried,
    )


def _resolve_hash(
    x: PathLike | None, hashes: dict[Path, str] | None, copies: Mapping[Path, Path] | None
) -> str | None:
    if x is None:
        return None
    s = str(x)
    if re.fullmatch(r"[0-9a-f]{64}", s) and not Path(s).exists():
        return s
    ckpt = Checkpoint(s)
    digests = {}
    for f in ckpt.files:
        h, copy = hashlib.sha256(), _Copy(f, copies.pop(f)) if copies and f in copies else None
        try:
            _hash_range(h, f, 0, f.stat().st_size, copy)
        finally:
            if copy is not None:
                copy.close()
        digests[f] = h.hexdigest()
        if hashes is not None:
            _record(hashes, {f: digests[f]} | ({copy.path: digests[f]} if copy else {}))
    return ckpt.sha256(digests)


def _record(hashes: dict[Path, str], digests: dict[Path, str]) -> None:
    """Add digests; a file read twice (as minuend and base, say) must have given the same bytes."""
    for path, digest in digests.items():
        if hashes.setdefault(path, digest) != digest:
            raise VectorOpError(f"{path} changed while it was being read; run the command again")


@contextlib.contextmanager
def _open_readers(
    ckpts: Mapping[str, Checkpoint], copies: Mapping[Path, Path] | None
) -> Iterator[dict[str, _HashingReader]]:
    """A hashing reader per role, in order, sharing one helper thread; closed when the output is done.
    Each file in `copies` is copied by the first reader of it (its entry taken out of a private dict)."""
    pool = ThreadPoolExecutor(1)
    copies = dict(copies or {})
    readers = {role: _HashingReader(c, pool, copies) for role, c in ckpts.items()}
    try:
        yield readers
    finally:
        for r in readers.values():
            r.close()
        pool.shutdown()


def _out_dtypes(ref: Checkpoint, names: Iterable[str], out_as: str | None) -> dict[str, str]:
    """`--out-dtype` for the float tensors among `names` (none given: each keeps `ref`'s dtype)."""
    return {n: out_as for n in names if out_as and ref.specs[n].is_float}


def _carry_source(carry_from: PathLike | None, ref: Checkpoint) -> Path:
    """Where a folder output takes its non-weight files from: `carry_from`, else the reference input."""
    return Path(carry_from) if carry_from is not None else ref.path


def _filters_meta(include: Sequence[str] | None, exclude: Sequence[str] | None) -> dict[str, str]:
    return {
        "capvector.include": json.dumps(list(include or [])),
        "capvector.exclude": json.dumps(list(exclude or [])),
    }


def _same_or_raise(name: str, role: str, x: np.ndarray, others: Iterable[tuple[str, np.ndarray]]) -> None:
    """A non-float tensor is carried over as it is, so every input must hold the same values."""
    for other, y in others:
        if not np.array_equal(x, y):
            raise VectorOpError(f"non-float tensor {name!r} differs between {role} and {other}")


def extract(
    minuend: PathLike,
    subtrahend: PathLike,
    out: PathLike,
    include: Sequence[str] | None = None,
    exclude: Sequence[str] | None = None,
    base: PathLike | None = None,
    max_shard_bytes: int = DEFAULT_MAX_SHARD_BYTES,
    overwrite: bool = False,
    hashes: dict[Path, str] | None = None,
    copies: Mapping[Path, Path] | None = None,
    dtype: str | None = None,
    out_dtype: str | None = None,
    strip_prefix: str | None = None,
    add_prefix: str | None = None,
    carry_from: PathLike | None = None,
    card: Card | None = None,
    input_ids=None,
) -> Path:
    """Write the vector `minuend − subtrahend` (capability vector θ_ao − θ_ft, or task vector θ − θ_pt).

    `base` (a checkpoint path or a sha256) records the θ_pt the vector is meant for, so that `merge` can
    refuse another base: by its files' hash (`capvector.base_sha256`) and by its tensors' content hash
    (`capvector.base_content_sha256`, the same for the same weights as a file or a folder); for a task
    vector it is the subtrahend. With a filter the vector holds only the
    selected tensors and is marked `capvector.partial`. `hashes` receives the sha256 of every input file
    as it was read (a caller checks stored inputs with them); `copies` (input file -> new path) has a
    copy of each named file written as it is read, and `hashes` the sha256 of each copy path (a caller
    stores the copies under them: exactly the bytes computed from, read once).

    Real checkpoints: `dtype` (float32 | float64) is the dtype the difference is computed in, and lets
    float tensors of different dtypes meet (a bf16 fine-tune against an fp32 base); `out_dtype` the
    float dtype written (default: the minuend's). `strip_prefix` / `add_prefix` map the subtrahend's
    names onto the minuend's (`model.enc.weight` vs `enc.weight`); the vector has the minuend's names.
    A folder output gets the non-weight files of `carry_from` (default: the minuend, if a folder) and,
    with `card`, a README.md card (`Card`; `input_ids(role)` names an input's artifact id).
    """
    compute_as, out_as = compute_dtype(dtype), float_dtype(out_dtype)
    a, b = Checkpoint(minuend), Checkpoint(subtrahend)
    names = _extract_names(a, b, include, exclude, strip_prefix, add_prefix, compute_as)
    copies = dict(copies or {})  # each file is copied by the first reader of it (its entry taken out)
    base_hash = _resolve_hash(base, hashes, copies)
    meta = _extract_meta(a, names, include, exclude, base, base_hash)
    dtypes = _out_dtypes(a, names, out_as)
    with _open_readers({"minuend": a, "subtrahend": b}, copies) as readers:
        compute = functools.partial(_difference, *readers.values(), dtypes, compute_as, _Scratch())
        return _run(
            out, names, a, readers, meta, compute, max_shard_bytes, overwrite, hashes=hashes, dtypes=dtypes,
            carry_from=_carry_source(carry_from, a), card=_with_base(card, base_hash), input_ids=input_ids,
        )  # fmt: skip


def _extract_names(
    a: Checkpoint,
    b: Checkpoint,
    include: Sequence[str] | None,
    exclude: Sequence[str] | None,
    strip_prefix: str | None,
    add_prefix: str | None,
    compute_as: str | None,
) -> list[str]:
    """The tensors the vector holds, once the subtrahend's names are mapped onto the minuend's and both
    are checked to hold the same tensors (shapes, dtypes), before anything is read."""
    role = f"subtrahend {b.path}"
    b.rename(strip_prefix, add_prefix, role)
    _key_diff(a, b, role)
    names = select_names(a.keys(), include, exclude)
    _compare(a, b, role, names, compute_as)
    return names


def _extract_meta(
    a: Checkpoint,
    names: list[str],
    include: Sequence[str] | None,
    exclude: Sequence[str] | None,
    base: PathLike | None,
    base_hash: str | None,
) -> dict[str, str]:
    """A vector's metadata: its formula, its filters, whether it is partial, and the base it is meant for
    (by files' hash and, for a base read here, by content hash)."""
    base_content = Checkpoint(base).content_sha256() if base is not None and Path(base).exists() else None
    meta = {
        "capvector.kind": "vector",
        "capvector.formula": "minuend - subtrahend",
        "capvector.coefficients": json.dumps({"minuend": 1.0, "subtrahend": -1.0}),
        **_filters_meta(include, exclude),
        "capvector.partial": json.dumps(len(names) != len(a)),
    }
    if base_hash:
        meta["capvector.base_sha256"] = base_hash
    if base_content:
        meta["capvector.base_content_sha256"] = base_content
    return meta


def _with_base(card: Card | None, base_hash: str | None) -> Card | None:
    """The card naming the base the vector is meant for (an input that is not streamed)."""
    if card is None or not base_hash:
        return card
    return card.model_copy(update={"extra_inputs": {**card.extra_inputs, "base": base_hash}})


def _difference(
    ra: _HashingReader,
    rb: _HashingReader,
    dtypes: Mapping[str, str],
    compute_as: str | None,
    scratch: _Scratch,
    n: str,
) -> Iterator[np.ndarray]:
    """Tensor `n` of minuend − subtrahend, piece by piece, in the output's dtype."""
    ba, bb = _byte_bounds([ra.ckpt, rb.ckpt], n)
    da, db = ra.ckpt.specs[n].dtype, rb.ckpt.specs[n].dtype
    to, wide = dtypes.get(n, da), _wide_for(compute_as, da, db)
    for x, y in zip(ra.chunks(n, ba), rb.chunks(n, bb), strict=True):
        if da not in FLOATS:
            _same_or_raise(n, "minuend", x, [("subtrahend", y)])
            yield x
            continue
        # Never modify x or y in place: their bytes may still be being hashed in the helper thread.
        xw, yw = _to(x, da, wide, scratch, "x"), _to(y, db, wide, scratch, "y")
        acc = np.subtract(xw, yw, out=scratch("acc", x.size, wide))
        yield _cast_back(acc, to, n, [("minuend", x, da), ("subtrahend", y, db)], scratch)


def merge(
    base: PathLike,
    vectors: Sequence[tuple[PathLike, float]],
    out: PathLike,
    include: Sequence[str] | None = None,
    exclude: Sequence[str] | None = None,
    force: bool = False,
    max_shard_bytes: int = DEFAULT_MAX_SHARD_BYTES,
    overwrite: bool = False,
    hashes: dict[Path, str] | None = None,
    copies: Mapping[Path, Path] | None = None,
    dtype: str | None = None,
    out_dtype: str | None = None,
    strip_prefix: str | None = None,
    add_prefix: str | None = None,
    carry_from: PathLike | None = None,
    card: Card | None = None,
    input_ids=None,
) -> Path:
    """Write θ = base + Σ_i α_i·vector_i (θ_meta = θ_pt + α·γ); tensors outside the filter are base's.

    A vector must have exactly base's tensors (a `capvector.partial` vector: a subset), same shapes and
    dtypes. A vector whose metadata names another base is refused unless `force=True` (`--force`): it
    names its base by files' hash (`capvector.base_sha256`) and by content hash
    (`capvector.base_content_sha256`); either matching accepts base, so the same weights as a file or a
    folder are the same base. Base's file hash is computed while streaming, so that check happens at
    the end, before the output is renamed into place (the content hash is read only if it is needed).
    The output keeps base's metadata but for base's own provenance
    (`capvector.*` keys other than `CARRIED_KEYS`, which would be false of the output), so a merged policy
    checkpoint loads as its base does (`capvector.core.policies.base.load_policy`). `hashes`, `copies`: as in
    `extract`. `dtype`, `out_dtype` (default: base's dtype), `strip_prefix` / `add_prefix` (applied to
    the vectors' names, to match base's), `carry_from` (default: base, if a folder), `card`,
    `input_ids`: as in `extract`.
    """
    _check_coefficients(vectors)
    compute_as, out_as = compute_dtype(dtype), float_dtype(out_dtype)
    b = Checkpoint(base)
    vecs = _vectors_fitting(b, vectors, strip_prefix, add_prefix, compute_as)
    selected = set(select_names(b.keys(), include, exclude))
    dtypes = _out_dtypes(b, b.keys(), out_as)
    with _open_readers({"base": b, **{f"vector_{i}": v for i, (v, _) in enumerate(vecs)}}, copies) as readers:
        weighted = [(i, readers[f"vector_{i}"], a) for i, (_, a) in enumerate(vecs)]
        compute = functools.partial(
            _sum_pieces, readers["base"], weighted, selected, dtypes, compute_as, _Scratch()
        )
        return _run(
            out, b.keys(), b, readers, _merge_meta(b, vecs, include, exclude), compute, max_shard_bytes,
            overwrite, functools.partial(_check_bases, b, vecs, force), hashes, dtypes=dtypes,
            carry_from=_carry_source(carry_from, b), card=_with_alphas(card, vecs), input_ids=input_ids,
        )  # fmt: skip


def _check_coefficients(vectors: Sequence[tuple[PathLike, float]]) -> None:
    if not vectors:
        raise VectorOpError("merge needs at least one (vector, coefficient) pair")
    bad = [f"vector {i}: {alpha}" for i, (_, alpha) in enumerate(vectors) if not math.isfinite(float(alpha))]
    if bad:  # NaN/inf would only show as a non-finite tensor once streaming reached it
        raise VectorOpError(f"merge coefficients must be finite numbers ({', '.join(bad)})")


def _vectors_fitting(
    b: Checkpoint,
    vectors: Sequence[tuple[PathLike, float]],
    strip_prefix: str | None,
    add_prefix: str | None,
    compute_as: str | None,
) -> list[tuple[Checkpoint, float]]:
    """The (vector, α) pairs, opened; each vector, its names mapped onto base's, must hold base's tensors
    (a partial one: some of them) with their shapes and dtypes."""
    vecs = [(Checkpoint(p), float(alpha)) for p, alpha in vectors]
    for i, (v, _) in enumerate(vecs):
        v.rename(strip_prefix, add_prefix, f"vector {i} ({v.path})")
        partial = json.loads(v.metadata.get("capvector.partial", "false"))
        _key_diff(b, v, f"vector {i} ({v.path})", allow_missing=partial)
        _compare(b, v, f"vector {i} ({v.path})", v.keys(), compute_as)
    return vecs


def _merge_meta(
    b: Checkpoint,
    vecs: Sequence[tuple[Checkpoint, float]],
    include: Sequence[str] | None,
    exclude: Sequence[str] | None,
) -> dict[str, str]:
    """Base's metadata but its own provenance (so a merged policy loads as its base does), the formula,
    the coefficients and the filters."""
    carried = {k: v for k, v in b.metadata.items() if not k.startswith("capvector.") or k in CARRIED_KEYS}
    return {
        **carried,
        "capvector.kind": "merged",
        "capvector.formula": "base + sum_i alpha_i * vector_i",
        "capvector.coefficients": json.dumps([a for _, a in vecs]),
        **_filters_meta(include, exclude),
    }


def _with_alphas(card: Card | None, vecs: Sequence[tuple[Checkpoint, float]]) -> Card | None:
    """The card with each vector's coefficient (those the caller gave win)."""
    if card is None:
        return None
    alphas = {f"vector_{i}": a for i, (_, a) in enumerate(vecs)}
    return card.model_copy(update={"alphas": {**alphas, **card.alphas}})


def _sum_pieces(
    rb: _HashingReader,
    weighted: Sequence[tuple[int, _HashingReader, float]],
    selected: set[str],
    dtypes: Mapping[str, str],
    compute_as: str | None,
    scratch: _Scratch,
    n: str,
) -> Iterator[np.ndarray]:
    """Tensor `n` of base + Σ α_i·vector_i, piece by piece, over the vectors that hold it (none when it
    is outside the filter: base's own, checked finite, or cast to the output's dtype)."""
    dtype = rb.ckpt.specs[n].dtype
    to = dtypes.get(n, dtype)
    users = [(i, r, a) for i, r, a in weighted if n in r.ckpt] if n in selected else []
    bounds = _byte_bounds([rb.ckpt, *(r.ckpt for _, r, _ in users)], n)
    kinds = [r.ckpt.specs[n].dtype for _, r, _ in users]
    wide = _wide_for(compute_as, dtype, *kinds)
    streams = [(i, r.chunks(n, bd), a, d) for (i, r, a), bd, d in zip(users, bounds[1:], kinds, strict=True)]
    for x in rb.chunks(n, bounds[0]):
        terms = [(i, next(it), a, d) for i, it, a, d in streams]
        if not terms and to == dtype:
            _finite_or_raise(x, dtype, n, "base")
            yield x
        elif dtype not in FLOATS:
            _same_or_raise(n, "base", x, [(f"vector {i}", y) for i, y, _, _ in terms])
            yield x
        else:
            yield _sum_piece(x, dtype, terms, to, wide, n, scratch)


def _sum_piece(
    x: np.ndarray,
    dtype: str,
    terms: Sequence[tuple[int, np.ndarray, float, str]],
    to: str,
    wide: type,
    name: str,
    scratch: _Scratch,
) -> np.ndarray:
    """One piece of base (`x`) plus its `terms` (vector index, piece, α, dtype), computed in `wide`, each
    α·vector rounded before it is added, then cast to `to`."""
    # Never modify x or y in place: their bytes may still be being hashed in the helper thread.
    xw, acc = _to(x, dtype, wide, scratch, "x"), scratch("acc", x.size, wide)
    if not terms:  # base only, cast to --out-dtype
        np.copyto(acc, xw)
    for j, (_, y, a, d) in enumerate(terms):
        yw = _to(y, d, wide, scratch, "y")
        term = np.multiply(yw, wide(a), out=scratch("term", x.size, wide))
        np.add(acc if j else xw, term, out=acc)
    inputs = [("base", x, dtype)] + [(f"vector {i}", y, d) for i, y, _, d in terms]
    return _cast_back(acc, to, name, inputs, scratch)


def _check_bases(
    b: Checkpoint, vecs: Sequence[tuple[Checkpoint, float]], force: bool, digests: dict[str, str]
) -> None:
    """Refuse a vector made for another base (unless `force`), once base's file hash is known (it is
    computed while streaming); base's content hash is read only when a file hash does not match."""
    base_content = functools.cache(b.content_sha256)
    for i, (v, _) in enumerate(vecs):
        want = v.metadata.get("capvector.base_sha256")
        want_content = v.metadata.get("capvector.base_content_sha256")
        if not (want or want_content) or want == digests["base"] or force:
            continue
        if base_content() in (want, want_content):
            continue
        named = (want_content or want)[:12]
        raise VectorOpError(
            f"vector {i} ({v.path}) was extracted for base {named}…, not {b.path} "
            f"(tensors {base_content()[:12]}…, files {digests['base'][:12]}…); "
            "pass --force to merge anyway"
        )


MEAN_METHODS = ("mean", "ties")
MEAN_FORMULAS = {
    "mean": "mean_i vector_i",
    "ties": "ties(vector_i): each trimmed to its top density by magnitude, sign of the sum elected, "
    "mean of the entries of that sign",
}
# float dtype -> (unsigned type of its bits, the bits but the sign, bits): |x| orders as these integers
_MAGNITUDE = {
    "F64": (np.uint64, 0x7FFF_FFFF_FFFF_FFFF, 64),
    "F32": (np.uint32, 0x7FFF_FFFF, 32),
    "F16": (np.uint16, 0x7FFF, 16),
    "BF16": (np.uint16, 0x7FFF, 16),
    "F8_E4M3": (np.uint8, 0x7F, 8),
    "F8_E5M2": (np.uint8, 0x7F, 8),
}


def check_mean_args(count: int, method: str, density: float) -> None:
    """`mean`'s arguments, checked before anything is read (the CLI calls it first too)."""
    if count < 2:
        raise VectorOpError(f"a mean needs at least 2 vectors, got {count}")
    if method not in MEAN_METHODS:
        raise VectorOpError(f"method must be one of {', '.join(MEAN_METHODS)}, got {method!r}")
    if not (isinstance(density, int | float) and math.isfinite(density) and 0 < density <= 1):
        raise VectorOpError(f"density must be a number in (0, 1], got {density!r}")


def mean(
    vectors: Sequence[PathLike],
    out: PathLike,
    method: Literal["mean", "ties"] = "mean",
    density: float = 0.2,
    max_shard_bytes: int = DEFAULT_MAX_SHARD_BYTES,
    overwrite: bool = False,
    hashes: dict[Path, str] | None = None,
    copies: Mapping[Path, Path] | None = None,
) -> Path:
    """Write the mean of K ≥ 2 vectors (γ̄_K of K seed draws of θ_ao − θ_ft: the seed noise averages out),
    or with `method="ties"` their TIES merge (Yadav et al. 2023, as mergekit's `ties`).

    The vectors must hold the same tensors (shapes, dtypes); they are streamed together, a piece of
    each tensor of each at a time (memory: K pieces, whatever K's checkpoints weigh). `mean`:
    (Σ_i vector_i) / K, in float32 (float64 for F64). `ties`, per tensor: each vector keeps its
    entries whose magnitude is at least its k-th largest, k = ⌈density·numel⌉ (entries tied with the
    k-th are all kept), the others become 0; each entry's sign is elected as the sign of the sum of the
    kept values; the result is the mean of the kept values of that sign (0 where the sum is 0, a tie,
    or nothing was kept: unlike mergekit, which elects + on a tie). The threshold is found exactly in
    bounded memory: a tensor of one piece is partitioned; a larger one costs one more read per 16 bits
    of its dtype (a radix selection on the magnitude's bits). Non-float tensors must be equal in all
    (carried over). The same file (or the same bytes) given twice is refused: each draw counts once.
    The output is a vector (`capvector.kind`), naming its inputs `vector_0`… by sha256, with their
    `capvector.base_sha256` (inputs naming different bases are refused), `capvector.partial` if any
    is, and their `capvector.include`/`exclude` where all agree. `hashes`, `copies`: as in `extract`.
    """
    check_mean_args(len(vectors), method, density)
    vecs = [Checkpoint(p) for p in vectors]
    _check_vectors_match(vecs)
    meta, ref = _mean_meta(vecs, method, density), vecs[0]
    with _open_readers({f"vector_{i}": v for i, v in enumerate(vecs)}, copies) as readers:
        compute = functools.partial(_mean_pieces, list(readers.values()), method, density, _Scratch())
        return _run(
            out, ref.keys(), ref, readers, meta, compute, max_shard_bytes, overwrite, _refuse_repeats, hashes
        )


def _check_vectors_match(vecs: Sequence[Checkpoint]) -> None:
    """Each vector given once, all with vector 0's tensors, shapes and dtypes."""
    first: dict[Path, int] = {}
    for i, v in enumerate(vecs):
        j = first.setdefault(v.path.resolve(), i)
        if j != i:
            raise VectorOpError(
                f"vector {j} and vector {i} are the same checkpoint ({v.path}): each counts once"
            )
    ref = vecs[0]
    for i, v in enumerate(vecs[1:], 1):
        role = f"vector {i} ({v.path}; vector 0 is {ref.path})"
        _key_diff(ref, v, role)
        _compare(ref, v, role, ref.keys())


def _mean_meta(vecs: Sequence[Checkpoint], method: str, density: float) -> dict[str, str]:
    """A mean's metadata: its method, and what its inputs agree on (partial, filters, their base)."""
    by_content = all("capvector.base_content_sha256" in v.metadata for v in vecs)  # else by files
    base_key = "capvector.base_content_sha256" if by_content else "capvector.base_sha256"
    bases = _bases_named(vecs, base_key)
    partial = any(json.loads(v.metadata.get("capvector.partial", "false")) for v in vecs)
    meta = {
        "capvector.kind": "vector",
        "capvector.formula": MEAN_FORMULAS[method],
        "capvector.method": method,
        "capvector.partial": json.dumps(partial),
    }
    if method == "mean":
        meta["capvector.coefficients"] = json.dumps([1 / len(vecs)] * len(vecs))
    else:
        meta["capvector.density"] = json.dumps(density)
    for key in ("capvector.include", "capvector.exclude"):
        values = {v.metadata.get(key) for v in vecs}
        if len(values) == 1 and None not in values:
            meta[key] = values.pop()
    if bases:
        meta[base_key] = next(iter(bases))
        if by_content and (files := vecs[0].metadata.get("capvector.base_sha256")):
            meta["capvector.base_sha256"] = files
    return meta


def _bases_named(vecs: Sequence[Checkpoint], key: str) -> dict[str, list[int]]:
    """base (as metadata `key` names it) -> the vectors made for it; different bases are refused."""
    bases: dict[str, list[int]] = {}
    for i, v in enumerate(vecs):
        if want := v.metadata.get(key):
            bases.setdefault(want, []).append(i)
    if len(bases) > 1:
        named = "; ".join(f"{b[:12]}… (vector {', '.join(map(str, ix))})" for b, ix in bases.items())
        raise VectorOpError(f"the vectors were extracted for different bases: {named}")
    return bases


def _mean_pieces(
    readers: Sequence[_HashingReader], method: str, density: float, scratch: _Scratch, n: str
) -> Iterator[np.ndarray]:
    """Tensor `n` of the mean (or TIES merge) of the vectors, piece by piece. TIES needs each vector's
    magnitude threshold first: found in a look-ahead pass when the tensor spans several pieces."""
    vecs = [r.ckpt for r in readers]
    spec, bounds = vecs[0].specs[n], vecs[0].chunk_bounds(n, CHUNK_BYTES)
    dtype, numel = spec.dtype, spec.nbytes // spec.itemsize
    ties = method == "ties" and dtype in FLOATS
    keep = _keep_count(numel, density)
    limits = None  # per vector, the magnitude (as its bits) an entry needs to be kept
    if ties and len(bounds) > 1:
        limits = [_kth_largest_streamed(r, n, bounds, keep, scratch) for r in readers]
    for xs in zip(*(r.chunks(n, bounds) for r in readers), strict=True):
        if dtype not in FLOATS:
            _same_or_raise(n, "vector 0", xs[0], [(f"vector {i}", y) for i, y in enumerate(xs[1:], 1)])
            yield xs[0]
            continue
        # Never modify an input piece in place: its bytes may still be being hashed in the helper thread.
        inputs = [(f"vector {i} ({v.path})", x, dtype) for i, (v, x) in enumerate(zip(vecs, xs, strict=True))]
        if ties:
            acc = _ties_checked(xs, inputs, dtype, n, keep, limits, scratch)
        else:
            acc = _mean_piece(xs, dtype, scratch)
        yield _cast_back(acc, dtype, n, inputs, scratch)


def _ties_checked(
    xs: Sequence[np.ndarray],
    inputs: list[tuple[str, np.ndarray, str]],
    dtype: str,
    name: str,
    keep: int,
    limits: list[int] | None,
    scratch: _Scratch,
) -> np.ndarray:
    """`_ties_piece` once every input is finite (NaN would compare as neither sign and vanish from the
    result); without `limits` the tensor is this one piece, and its thresholds are found here."""
    for role, x, _ in inputs:
        _finite_or_raise(x, dtype, name, role)
    if limits is None:
        limits = [_kth_largest(_magnitude(x, dtype), keep) for x in xs]
    return _ties_piece(xs, dtype, limits, scratch)


def _refuse_repeats(digests: dict[str, str]) -> None:
    """Two inputs with the same bytes (a copy under another name) would count one draw twice."""
    seen: dict[str, str] = {}
    for role, digest in digests.items():
        if (other := seen.setdefault(digest, role)) != role:
            raise VectorOpError(
                f"{other.replace('_', ' ')} and {role.replace('_', ' ')} are the same bytes "
                f"(sha256 {digest[:12]}…): each vector counts once in a mean"
            )


def _mean_piece(xs: Sequence[np.ndarray], dtype: str, scratch: _Scratch) -> np.ndarray:
    k, wide = xs[0].size, _wide(dtype)
    acc = scratch("acc", k, wide)
    np.copyto(acc, _widen(xs[0], dtype, scratch("y", k, wide)))
    for y in xs[1:]:
        np.add(acc, _widen(y, dtype, scratch("y", k, wide)), out=acc)
    return np.divide(acc, len(xs), out=acc)


def _ties_piece(xs: Sequence[np.ndarray], dtype: str, limits: Sequence[int], scratch: _Scratch) -> np.ndarray:
    """TIES on one piece: per vector, entries below its magnitude limit dropped; the sums and counts of
    the kept positive and negative entries; where the sum of all kept is > 0 the mean of the positive
    ones, < 0 of the negative ones, else 0. Plain arithmetic on whole arrays (masked ufuncs, `where=`,
    are several times slower)."""
    k, wide = xs[0].size, _wide(dtype)
    sums = {s: scratch(f"sum{s}", k, wide) for s in "+-"}
    counts = {s: scratch(f"count{s}", k, wide) for s in "+-"}
    for a in (*sums.values(), *counts.values()):
        a.fill(0)
    kept, part, sel = scratch("kept", k, wide), scratch("part", k, wide), scratch("sel", k, np.bool_)
    for x, limit in zip(xs, limits, strict=True):
        np.greater_equal(_magnitude(x, dtype, scratch("key", k, _MAGNITUDE[dtype][0])), limit, out=sel)
        np.multiply(_widen(x, dtype, scratch("x", k, wide)), sel, out=kept)  # finite: 0 where dropped
        for s, side, clip in (("+", np.greater, np.maximum), ("-", np.less, np.minimum)):
            np.add(sums[s], clip(kept, 0, out=part), out=sums[s])
            np.add(counts[s], side(kept, 0, out=sel), out=counts[s])
    total = np.add(sums["+"], sums["-"], out=scratch("total", k, wide))
    for s, side in (("+", np.greater), ("-", np.less)):
        np.divide(sums[s], np.maximum(counts[s], 1, out=counts[s]), out=sums[s])  # the mean of that sign
        np.multiply(sums[s], side(total, 0, out=sel), out=sums[s])  # where that sign is elected, else 0
    return np.add(sums["+"], sums["-"], out=scratch("acc", k, wide))


def _keep_count(numel: int, density: float) -> int:
    """⌈density·numel⌉, with density as written (0.3 of 10 is 3, not the 4 that 0.3·10 in floats gives)."""
    return min(numel, math.ceil(Decimal(repr(float(density))) * numel))


def _magnitude(x: np.ndarray, dtype: str, out: np.ndarray | None = None) -> np.ndarray:
    """|x| as unsigned integers in the same order (a float's bits without its sign; NaN above Inf)."""
    bits, mask, _ = _MAGNITUDE[dtype]
    return np.bitwise_and(x.view(bits), bits(mask), out=out)


def _kth_largest(keys: np.ndarray, k: int) -> int:
    """The k-th largest of `keys` (0 if there are none: every entry is kept)."""
    if k <= 0 or keys.size == 0:
        return 0
    return int(np.partition(keys, keys.size - k)[keys.size - k])


def _kth_largest_streamed(
    reader: _HashingReader, name: str, bounds: list[tuple[int, int]], k: int, scratch: _Scratch
) -> int:
    """`_kth_largest` of one tensor's magnitudes, read piece by piece: a radix selection, 16 bits of the
    key per pass (a histogram of the next 16 bits among the keys that share the bits chosen so far)."""
    if k <= 0:
        return 0
    dtype = reader.ckpt.specs[name].dtype
    bits, _, nbits = _MAGNITUDE[dtype]
    width = min(16, nbits)
    buf = scratch("peek", max(e - b for b, e in bounds), np.uint8)
    prefix, rank = 0, k  # rank: which largest among the keys that start with `prefix`
    for shift in range(nbits - width, -1, -width):
        hist = np.zeros(1 << width, np.int64)
        for x in reader.peek(name, bounds, buf):
            keys = _magnitude(x, dtype, scratch("keys", x.size, bits))
            if shift + width == nbits:  # the top digit (the sign bit is 0): no prefix yet
                digits = np.right_shift(keys, bits(shift), out=keys)
            else:  # only the keys that start with `prefix`: few, past the first pass
                high = np.right_shift(keys, bits(shift + width), out=scratch("high", x.size, bits))
                match = np.equal(high, prefix, out=scratch("match", x.size, np.bool_))
                digits = (keys[match] >> bits(shift)) & bits((1 << width) - 1)
            hist += np.bincount(digits, minlength=1 << width)
        from_top = np.cumsum(hist[::-1])
        i = int(np.searchsorted(from_top, rank))  # the first digit, from the top, that reaches `rank`
        digit = (1 << width) - 1 - i
        rank -= int(from_top[i] - hist[digit])
        prefix = (prefix << width) | digit
    return prefix


def null_vector(
    vector: PathLike,
    out: PathLike,
    seed: int,
    max_shard_bytes: int = DEFAULT_MAX_SHARD_BYTES,
    overwrite: bool = False,
    hashes: dict[Path, str] | None = None,
) -> Path:
    """A random vector with `vector`'s per-tensor L2 norms: the control "any direction of γ's size".

    Each float tensor is Gaussian noise (numpy's PCG64 seeded with `seed`, tensors in the file's order)
    rescaled to the norm of the same tensor of `vector`; non-float tensors are copied. The base the
    vector was made for carries over, so it merges into the same θ_pt.
    """
    v = Checkpoint(vector)
    names = list(v.specs)
    pool = ThreadPoolExecutor(1)
    reader = _HashingReader(v, pool)
    rng = np.random.default_rng(seed)

    def compute(n: str) -> Iterator[np.ndarray]:
        dtype = v.specs[n].dtype
        bounds = v.chunk_bounds(n, CHUNK_BYTES)
        if dtype not in FLOATS:
            for x in reader.chunks(n, bounds):
                yield x
            return
        squares, size = 0.0, 0
        for x in reader.chunks(n, bounds):
            wide = _widen(x, dtype).astype(np.float64)
            squares += stable_dot(wide, wide)
            size += x.size
        noise = rng.standard_normal(size)
        length = math.sqrt(stable_dot(noise, noise))
        noise *= math.sqrt(squares) / length if length > 0 else 0.0
        yield _narrow(noise.astype(_wide(dtype)), dtype)

    meta = {
        "capvector.kind": "vector",
        "capvector.formula": "random, with the per-tensor norms of vector",
        "capvector.seed": str(seed),
        **{
            k: v.metadata[k]
            for k in (
                "capvector.include",
                "capvector.exclude",
                "capvector.partial",
                "capvector.base_sha256",
                "capvector.base_content_sha256",
            )
            if k in v.metadata
        },
    }
    try:
        return _run(
            out, names, v, {"vector": reader}, meta, compute, max_shard_bytes, overwrite, hashes=hashes
        )
    finally:
        reader.close()
        pool.shutdown()


class VectorStat(BaseModel):
    """One row of `stats`: a tensor, a module group (name prefix), or everything (`level="all"`)."""

    level: Literal["tensor", "group", "all"]
    name: str
    numel: int
    l2: float
    base_l2: float | None = None
    relative_norm: float | None = None  # ‖γ‖ / ‖θ_base‖
    cosine: float | None = None  # cos(γ, reference vector)
    sign_agreement: float | None = None  # share of elements, both non-zero, with equal signs


def stable_dot(a: np.ndarray, b: np.ndarray, out: np.ndarray | None = None) -> float:
    """a · b in float64 with the same bits whatever the thread count and BLAS: the products summed by
    numpy's pairwise summation, whose order follows the length alone. A BLAS dot splits its sum among
    its threads (OpenBLAS above 10,000 elements), so the last digits of a norm, hence the id of the
    `vector_stats` of γ, followed the thread count (one on a Dask worker, several in the step pool).
    `out`: a float64 buffer of a's size for the products."""
    return float(np.add.reduce(np.multiply(a, b, out=out)))


def group_of(name: str, depth: int) -> str:
    return ".".join(name.split(".")[:depth])


def stats(
    vector: PathLike,
    base: PathLike | None = None,
    reference_vector: PathLike | None = None,
    include: Sequence[str] | None = None,
    exclude: Sequence[str] | None = None,
    group_depth: int = 2,
) -> list[VectorStat]:
    """Norms, norms relative to base, cosine and sign agreement with a reference (e.g. θ_ft − θ_pt).

    Rows per float tensor, per group (the first `group_depth` dotted components of the name) and one
    overall row; group values are exact aggregates (sums of squares and dot products), not averages.
    Tensors are read in pieces of about `CHUNK_BYTES`, so memory stays a few of those whatever their size.
    """
    v = Checkpoint(vector)
    names = [n for n in select_names(v.keys(), include, exclude) if _is_float(v.specs[n])]
    others = {}
    for role, p in (("base", base), ("reference_vector", reference_vector)):
        if p is not None:
            c = Checkpoint(p)
            missing = [n for n in names if n not in c]
            if missing:
                raise VectorOpError(f"{len(missing)} tensor(s) missing from {role} {c.path}: {_few(missing)}")
            bad = [n for n in names if c.specs[n].shape != v.specs[n].shape]
            if bad:
                raise VectorOpError(f"{len(bad)} tensor(s) of {role} differ in shape: {_few(bad)}")
            others[role] = c
    fields = ("numel", "sq", "bsq", "dot", "rsq", "agree", "both")
    acc: dict[tuple[str, str], dict[str, float]] = {}
    rows = []
    buffers: dict[str, np.ndarray] = {}
    for n in names:
        s = _tensor_sums(n, v, others, buffers)
        rows.append(_row("tensor", n, s, others))
        for key in (("group", group_of(n, group_depth)), ("all", "*")):
            tot = acc.setdefault(key, dict.fromkeys(fields, 0.0))
            for f in fields:
                tot[f] += s[f]
    rows += [_row(level, name, s, others) for (level, name), s in acc.items()]
    return rows


def _tensor_sums(
    name: str, vector: Checkpoint, others: dict[str, Checkpoint], buffers: dict[str, np.ndarray]
) -> dict[str, float]:
    """One tensor's sums for `stats`, streamed in pieces of about `CHUNK_BYTES` (per input, whatever its
    dtype): memory does not grow with the tensor. Each piece is widened to float64 and its sums (in
    float64, `_dot`: no BLAS, the same bits on any number of threads) are added up in Python floats."""
    ckpts = {"vector": vector, **others}
    item = max(c.specs[name].itemsize for c in ckpts.values())
    step = max(1, CHUNK_BYTES // item)
    s = dict.fromkeys(("numel", "sq", "bsq", "dot", "rsq", "agree", "both"), 0.0)
    numel = vector.specs[name].nbytes // vector.specs[name].itemsize
    s["numel"] = numel
    for i in range(0, numel, step):
        j = min(i + step, numel)
        g = _float64_chunk(vector, name, i, j, buffers, "vector")
        if not _all_finite(g):
            raise VectorOpError(f"NaN or Inf in tensor {name!r} of vector")
        products = buffers.get("products")
        if products is None or products.size < g.size:
            products = buffers["products"] = np.empty(max(g.size, step), np.float64)
        products = products[: g.size]
        s["sq"] += stable_dot(g, g, products)
        if "base" in others:
            w = _float64_chunk(others["base"], name, i, j, buffers, "base")
            s["bsq"] += stable_dot(w, w, products)
        if "reference_vector" in others:
            r = _float64_chunk(others["reference_vector"], name, i, j, buffers, "reference_vector")
            s["rsq"] += stable_dot(r, r, products)
            s["dot"] += stable_dot(g, r, products)
            sg, sr = np.sign(g), np.sign(r)
            both = (sg != 0) & (sr != 0)
            s["both"] += float(np.count_nonzero(both))
            s["agree"] += float(np.count_nonzero((sg == sr) & both))
    return s


def _float64_chunk(
    ckpt: Checkpoint, name: str, begin: int, end: int, buffers: dict[str, np.ndarray], role: str
) -> np.ndarray:
    """Elements [begin, end) of one tensor as float64, read into a buffer reused from piece to piece."""
    spec = ckpt.specs[name]
    nbytes = (end - begin) * spec.itemsize
    buf = buffers.get(role)
    if buf is None or buf.size < nbytes:
        buf = buffers[role] = np.empty(max(nbytes, CHUNK_BYTES), np.uint8)
    raw = _read(spec.file, None, spec.begin + begin * spec.itemsize, buf[:nbytes])
    return _widen(raw.view(STORAGE[spec.dtype]), spec.dtype).astype(np.float64, copy=False)


def tensor_float64(ckpt: Checkpoint, name: str) -> np.ndarray:
    """One whole tensor as float64 in its shape, its stored values converted as `stats` converts its
    pieces: for a computation that needs the tensor at once (a spectrum), one tensor at a time."""
    spec = ckpt.specs[name]
    raw = ckpt.read_bytes(name).view(STORAGE[spec.dtype])
    return _widen(raw, spec.dtype).astype(np.float64, copy=False).reshape(spec.shape)


def _row(level: str, name: str, s: dict[str, float], others: dict) -> VectorStat:
    l2 = math.sqrt(s["sq"])
    row = VectorStat(level=level, name=name, numel=int(s["numel"]), l2=l2)
    if "base" in others:
        row.base_l2 = math.sqrt(s["bsq"])
        row.relative_norm = l2 / row.base_l2 if row.base_l2 > 0 else None
    if "reference_vector" in others:
        denom = l2 * math.sqrt(s["rsq"])
        row.cosine = s["dot"] / denom if denom > 0 else None
        row.sign_agreement = s["agree"] / s["both"] if s["both"] > 0 else None
    return row
