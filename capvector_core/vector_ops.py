"""Streaming capability-vector arithmetic on safetensors checkpoints: `extract`, `merge`, `stats`.

All three walk the checkpoints tensor by tensor (memory bounded by a few tensors), so they work on any
safetensors checkpoint, including a sharded Hugging Face one. Conventions:
- float16/bfloat16 are computed in float32 and written back in their own dtype (float64 stays float64);
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
  metadata (its policy config: a merged policy loads like its base; see `merge`).

Name filters: `include`/`exclude` are lists of patterns in the project's one syntax
(`capvector_core.module_patterns`, shared with LoRA targets): a shell-style glob on the whole name (`*`
also crosses dots: `backbone.*`) or on its trailing dotted components (`attn.*_proj.weight`), or, prefixed
with `re:`, a Python regular expression that must match the whole name (`re:blocks\\.[0-3]\\..*`). A tensor
is selected when it matches some include pattern (or there is none) and no exclude pattern. A pattern that
matches no tensor at all, or a selection that is empty, is an error (it is almost always a typo).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Literal

import torch
from pydantic import BaseModel

from capvector_core import module_patterns
from capvector_core.safetensors_io import (
    DEFAULT_MAX_SHARD_BYTES,
    Checkpoint,
    CheckpointError,
    ShardedWriter,
    TensorSpec,
    _few,
)

PathLike = str | os.PathLike
_PLACEHOLDER = "0" * 64
CHUNK_BYTES = 4 << 20  # tensors are processed in pieces of this size: memory does not grow with them
# Base metadata a merge carries (besides base's non-`capvector.` keys): the policy config, so a merged
# policy checkpoint loads like its base. Equal to `capvector_core.policy.CONFIG_METADATA_KEY` (tested).
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
    return spec.torch_dtype.is_floating_point


def _compare(ref: Checkpoint, other: Checkpoint, role: str, names: Iterable[str]) -> None:
    """Shapes and dtypes of `names` must agree; raise naming a few offending tensors and the count."""
    bad = []
    for n in names:
        a, b = ref.specs[n], other.specs[n]
        if a.shape != b.shape or a.dtype != b.dtype:
            bad.append(f"{n} ({a.dtype}{list(a.shape)} vs {b.dtype}{list(b.shape)})")
    if bad:
        raise VectorOpError(f"{len(bad)} tensor(s) of {role} differ in shape or dtype: {', '.join(bad[:5])}")


def _key_diff(ref: Checkpoint, other: Checkpoint, role: str, allow_missing: bool = False) -> None:
    extra = [k for k in other.keys() if k not in ref]
    missing = [] if allow_missing else [k for k in ref.keys() if k not in other]
    msgs = []
    if missing:
        msgs.append(f"{len(missing)} tensor(s) missing from {role}: {_few(missing)}")
    if extra:
        msgs.append(f"{len(extra)} unexpected tensor(s) in {role}: {_few(extra)}")
    if msgs:
        raise VectorOpError("; ".join(msgs))


class _HashingReader:
    """Reads tensors of one checkpoint and hashes its files from those same bytes, in a helper thread.

    Tensors read in storage order feed the running sha256 of their file; anything out of order (or not
    read at all) is hashed from disk at the end, so the digest is always the file's true sha256.
    """

    def __init__(self, ckpt: Checkpoint, pool: ThreadPoolExecutor):
        self.ckpt = ckpt
        self.pool = pool
        self.state: dict[Path, list] = {}
        self.pending: Future | None = None
        for f in ckpt.files:
            h = hashlib.sha256()
            with open(f, "rb") as fh:
                head = fh.read(8)
                head += fh.read(int.from_bytes(head, "little"))
            h.update(head)
            self.state[f] = [h, len(head)]

    def chunks(self, name: str, bounds: list[tuple[int, int]]) -> Iterator[torch.Tensor]:
        """Flat typed pieces of one tensor, read (and hashed) in the byte ranges `bounds`."""
        spec = self.ckpt.specs[name]
        for b, e in bounds:
            raw = self.ckpt.read_raw(name, b, e)
            st = self.state[spec.file]
            if st[1] is not None and st[1] <= spec.begin + b:
                self._wait()
                if st[1] < spec.begin + b:  # bytes skipped (tensors not needed, padding): hash from disk
                    _hash_range(st[0], spec.file, st[1], spec.begin + b)
                self.pending = self.pool.submit(st[0].update, memoryview(raw.numpy()))
                st[1] = spec.begin + e
            else:
                st[1] = None  # read out of order: hash the whole file from disk at the end
            yield raw.view(spec.torch_dtype)

    def _wait(self) -> None:
        if self.pending is not None:
            self.pending.result()
            self.pending = None

    def sha256(self) -> str:
        self._wait()
        done = {}
        for f, (h, pos) in self.state.items():
            if pos is not None:
                _hash_range(h, f, pos, f.stat().st_size)
                done[f] = h.hexdigest()
        return self.ckpt.sha256(done)


def _hash_range(h, path: Path, begin: int, end: int, chunk: int = 8 << 20) -> None:
    with open(path, "rb") as f:
        f.seek(begin)
        while begin < end:
            data = f.read(min(chunk, end - begin))
            if not data:
                break
            h.update(data)
            begin += len(data)


def _sum_is_finite(t: torch.Tensor) -> bool:
    # A sum is non-finite iff some element is (NaN/Inf propagate): far cheaper than isfinite().all().
    wide = torch.float64 if t.dtype == torch.float64 else torch.float32
    return math.isfinite(float(t.sum(dtype=wide)))


def _finite_or_raise(t: torch.Tensor, name: str, role: str) -> None:
    if t.is_floating_point() and not _sum_is_finite(t) and not bool(torch.isfinite(t).all()):
        raise VectorOpError(f"NaN or Inf in tensor {name!r} of {role}")


def _cast_back(acc: torch.Tensor, dtype: torch.dtype, name: str, inputs: list[tuple[str, torch.Tensor]]):
    """Cast a float32/64 result to the output dtype; if it is not finite, name the input responsible."""
    out = acc if acc.dtype == dtype else acc.to(dtype)
    if not _sum_is_finite(out) and not bool(torch.isfinite(out).all()):
        for role, t in inputs:
            _finite_or_raise(t, name, role)
        raise VectorOpError(f"result for tensor {name!r} overflows {dtype}")
    return out


def _inputs_meta(readers: dict[str, _HashingReader]) -> dict[str, dict[str, str]]:
    """role -> {"sha256": ...}: content digests only. A path (a store's, a home's, a user's folder) would
    make the output's bytes, so its content id, depend on where the inputs happened to be read from."""
    return {role: {"sha256": _PLACEHOLDER} for role in readers}


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
) -> Path:
    """Stream `compute(name) -> flat pieces` for every name into `out`, then fill in the input hashes."""
    inputs = _inputs_meta(readers)
    metadata = {**metadata, "capvector.inputs": json.dumps(inputs, sort_keys=True)}
    specs = {n: (ref.specs[n].torch_dtype, ref.specs[n].shape) for n in names}
    with ShardedWriter(out, specs, metadata, max_shard_bytes, overwrite) as w:
        for n in w.order:
            w.write_chunks(n, compute(n))
        digests = {role: r.sha256() for role, r in readers.items()}
        if check is not None:
            check(digests)
        for role, d in digests.items():
            inputs[role]["sha256"] = d
        w.set_metadata("capvector.inputs", json.dumps(inputs, sort_keys=True))
    return Path(out)


def _resolve_hash(x: PathLike | None) -> str | None:
    if x is None:
        return None
    s = str(x)
    if re.fullmatch(r"[0-9a-f]{64}", s) and not Path(s).exists():
        return s
    return Checkpoint(s).sha256()


def extract(
    minuend: PathLike,
    subtrahend: PathLike,
    out: PathLike,
    include: Sequence[str] | None = None,
    exclude: Sequence[str] | None = None,
    base: PathLike | None = None,
    max_shard_bytes: int = DEFAULT_MAX_SHARD_BYTES,
    overwrite: bool = False,
) -> Path:
    """Write the vector `minuend − subtrahend` (capability vector θ_ao − θ_ft, or task vector θ − θ_pt).

    `base` (a checkpoint path or a sha256) records the θ_pt the vector is meant for, so that `merge` can
    refuse another base; for a task vector it is the subtrahend. With a filter the vector holds only the
    selected tensors and is marked `capvector.partial`.
    """
    a, b = Checkpoint(minuend), Checkpoint(subtrahend)
    _key_diff(a, b, f"subtrahend {b.path}")
    names = select_names(a.keys(), include, exclude)
    _compare(a, b, f"subtrahend {b.path}", names)
    base_hash = _resolve_hash(base)
    pool = ThreadPoolExecutor(1)
    ra, rb = _HashingReader(a, pool), _HashingReader(b, pool)

    def compute(n: str) -> Iterator[torch.Tensor]:
        bounds = a.chunk_bounds(n, CHUNK_BYTES)
        for x, y in zip(ra.chunks(n, bounds), rb.chunks(n, bounds), strict=True):
            if not x.is_floating_point():
                if not torch.equal(x, y):
                    raise VectorOpError(f"non-float tensor {n!r} differs between minuend and subtrahend")
                yield x
                continue
            # Never modify x or y in place: their bytes may still be being hashed in the helper thread.
            wide = torch.float64 if x.dtype == torch.float64 else torch.float32
            xw = x.to(wide)
            acc = xw.sub(y) if xw is x else xw.sub_(y.to(wide))
            yield _cast_back(acc, x.dtype, n, [("minuend", x), ("subtrahend", y)])

    meta = {
        "capvector.kind": "vector",
        "capvector.formula": "minuend - subtrahend",
        "capvector.coefficients": json.dumps({"minuend": 1.0, "subtrahend": -1.0}),
        "capvector.include": json.dumps(list(include or [])),
        "capvector.exclude": json.dumps(list(exclude or [])),
        "capvector.partial": json.dumps(len(names) != len(a)),
    }
    if base_hash:
        meta["capvector.base_sha256"] = base_hash
    try:
        readers = {"minuend": ra, "subtrahend": rb}
        return _run(out, names, a, readers, meta, compute, max_shard_bytes, overwrite)
    finally:
        pool.shutdown()


def merge(
    base: PathLike,
    vectors: Sequence[tuple[PathLike, float]],
    out: PathLike,
    include: Sequence[str] | None = None,
    exclude: Sequence[str] | None = None,
    force: bool = False,
    max_shard_bytes: int = DEFAULT_MAX_SHARD_BYTES,
    overwrite: bool = False,
) -> Path:
    """Write θ = base + Σ_i α_i·vector_i (θ_meta = θ_pt + α·γ); tensors outside the filter are base's.

    A vector must have exactly base's tensors (a `capvector.partial` vector: a subset), same shapes and
    dtypes. A vector whose metadata names another base (`capvector.base_sha256`) is refused unless
    `force=True`; base's hash is computed while streaming, so that check happens at the end, before the
    output is renamed into place. The output keeps base's metadata but for base's own provenance
    (`capvector.*` keys other than `CARRIED_KEYS`, which would be false of the output), so a merged policy
    checkpoint loads as its base does (`capvector_core.policy.load_policy`).
    """
    if not vectors:
        raise VectorOpError("merge needs at least one (vector, coefficient) pair")
    bad = [f"vector {i}: {alpha}" for i, (_, alpha) in enumerate(vectors) if not math.isfinite(float(alpha))]
    if bad:  # NaN/inf would only show as a non-finite tensor once streaming reached it
        raise VectorOpError(f"merge coefficients must be finite numbers ({', '.join(bad)})")
    b = Checkpoint(base)
    vecs = [(Checkpoint(p), float(alpha)) for p, alpha in vectors]
    for i, (v, _) in enumerate(vecs):
        partial = json.loads(v.metadata.get("capvector.partial", "false"))
        _key_diff(b, v, f"vector {i} ({v.path})", allow_missing=partial)
        _compare(b, v, f"vector {i} ({v.path})", v.keys())
    names = b.keys()
    selected = set(select_names(names, include, exclude))
    pool = ThreadPoolExecutor(1)
    rb = _HashingReader(b, pool)
    rvs = [_HashingReader(v, pool) for v, _ in vecs]

    def compute(n: str) -> Iterator[torch.Tensor]:
        bounds = b.chunk_bounds(n, CHUNK_BYTES)
        users = [(i, r, a) for i, (r, (v, a)) in enumerate(zip(rvs, vecs, strict=True)) if n in v]
        if n not in selected:
            users = []
        streams = [(i, r.chunks(n, bounds), a) for i, r, a in users]
        for x in rb.chunks(n, bounds):
            terms = [(i, next(it), a) for i, it, a in streams]
            if not terms:
                _finite_or_raise(x, n, "base")
                yield x
                continue
            if not x.is_floating_point():
                for i, y, _ in terms:
                    if not torch.equal(x, y):
                        raise VectorOpError(f"non-float tensor {n!r} differs between base and vector {i}")
                yield x
                continue
            wide = torch.float64 if x.dtype == torch.float64 else torch.float32
            acc = None  # fresh memory: x and y may still be being hashed in the helper thread
            for _, y, a in terms:
                y = y.to(wide)
                acc = torch.add(x.to(wide), y, alpha=a) if acc is None else acc.add_(y, alpha=a)
            yield _cast_back(acc, x.dtype, n, [("base", x)] + [(f"vector {i}", y) for i, y, _ in terms])

    def check(digests: dict[str, str]) -> None:
        for i, (v, _) in enumerate(vecs):
            want = v.metadata.get("capvector.base_sha256")
            if want and want != digests["base"] and not force:
                raise VectorOpError(
                    f"vector {i} ({v.path}) was extracted for base {want[:12]}…, not {b.path} "
                    f"({digests['base'][:12]}…); pass force=True to merge anyway"
                )

    carried = {k: v for k, v in b.metadata.items() if not k.startswith("capvector.") or k in CARRIED_KEYS}
    meta = {
        **carried,
        "capvector.kind": "merged",
        "capvector.formula": "base + sum_i alpha_i * vector_i",
        "capvector.coefficients": json.dumps([a for _, a in vecs]),
        "capvector.include": json.dumps(list(include or [])),
        "capvector.exclude": json.dumps(list(exclude or [])),
    }
    readers = {"base": rb, **{f"vector_{i}": r for i, r in enumerate(rvs)}}
    try:
        return _run(out, names, b, readers, meta, compute, max_shard_bytes, overwrite, check)
    finally:
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
    for n in names:
        g = v.get(n).double().flatten()
        _finite_or_raise(g, n, "vector")
        s = dict.fromkeys(fields, 0.0)
        s["numel"], s["sq"] = g.numel(), float(g @ g)
        if "base" in others:
            w = others["base"].get(n).double().flatten()
            s["bsq"] = float(w @ w)
        if "reference_vector" in others:
            r = others["reference_vector"].get(n).double().flatten()
            s["rsq"], s["dot"] = float(r @ r), float(g @ r)
            sg, sr = torch.sign(g), torch.sign(r)
            both = (sg != 0) & (sr != 0)
            s["both"], s["agree"] = float(both.sum()), float(((sg == sr) & both).sum())
        rows.append(_row("tensor", n, s, others))
        for key in (("group", group_of(n, group_depth)), ("all", "*")):
            tot = acc.setdefault(key, dict.fromkeys(fields, 0.0))
            for f in fields:
                tot[f] += s[f]
    rows += [_row(level, name, s, others) for (level, name), s in acc.items()]
    return rows


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
