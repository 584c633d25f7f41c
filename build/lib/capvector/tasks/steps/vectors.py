"""Steps: extract a capability vector (with its statistics), average several (γ̄ of K draws), and merge
vectors into a base checkpoint.

Inputs are read once and hashed as they are read, then checked against their ids before anything is
registered (Workspace.stream): the integrity the `capvector vector` commands give their inputs."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from capvector.core.vectors import vector_ops
from capvector.core.vectors.vector_ops import VectorStat, group_of
from capvector.tasks.runtime.caching import selected_by
from capvector.tasks.runtime.step_kinds import StepCall, StepKind, step_task
from capvector.tasks.runtime.workspace import provenance


class VectorFilter(BaseModel):
    """Which tensors a vector covers (glob patterns on tensor names); empty means all."""

    model_config = ConfigDict(extra="forbid")
    include: list[str] | None = Field(
        None,
        description="tensors γ covers, by name (module_patterns syntax, e.g. `backbone.*`); the others "
        "stay at θ_pt in θ_meta; null: every tensor",
    )
    exclude: list[str] | None = Field(
        None, description="tensors left out of γ (module_patterns syntax); null: none"
    )


class MergeConfig(VectorFilter):
    alpha: float = Field(
        1.1, allow_inf_nan=False, description="θ_meta = θ_pt + α·γ (the paper's best α is 1.1)"
    )


def stat_rows(stats: list[VectorStat], group_depth: int = 2) -> list[dict[str, Any]]:
    """core `VectorStat` rows -> the catalogue's per-tensor rows (group rows keep their level)."""
    rows = []
    for s in stats:
        rows.append(
            {
                "tensor": s.name,
                "group": group_of(s.name, group_depth) if s.level == "tensor" else s.name,
                "numel": s.numel,
                "l2": s.l2,
                "rel_norm": s.relative_norm,
                "cosine_ref": s.cosine,
                "sign_agreement": s.sign_agreement,
                "level": s.level,
            }
        )
    return rows


def _extract(call: StepCall) -> str:
    """γ = minuend − subtrahend; with a `base` input, statistics against θ_pt and θ_ft − θ_pt."""
    workspace, inputs, flt = call.workspace, call.inputs, call.config
    roles = [r for r in ("minuend", "subtrahend", "base") if r in inputs]
    reads = workspace.stream({r: inputs[r] for r in roles})
    minuend, subtrahend, base = (reads.paths.get(r) for r in ("minuend", "subtrahend", "base"))
    meta = provenance()
    with workspace.scratch() as tmp:
        out = vector_ops.extract(
            minuend, subtrahend, tmp / "vector.safetensors", flt.include, flt.exclude, base=base,
            hashes=reads.hashes,
        )  # fmt: skip
        record = workspace.api.register_file(
            out,
            kind="vector",
            name=call.step,
            config={"formula": "minuend - subtrahend", **flt.model_dump(), "cache_key": call.key},
            parents=[(inputs[r], r) for r in roles],
            parent_hashes=reads.verified(),
            **meta,
        )
        reference = None
        if base is not None:
            reference = vector_ops.extract(
                subtrahend, base, tmp / "task_vector.safetensors", base=base, hashes=reads.hashes
            )
        stats = vector_ops.stats(out, base=base, reference_vector=reference)
    workspace.api.register_vector_stats(record.id, stat_rows(stats), **meta)
    return record.id


def _merge(call: StepCall) -> str:
    """θ = base + α·vector; the merged file keeps base's metadata, so it loads as the same policy type."""
    workspace, inputs, cfg = call.workspace, call.inputs, call.config
    reads = workspace.stream({r: inputs[r] for r in ("base", "vector")})
    with workspace.scratch() as tmp:
        merged = vector_ops.merge(
            reads.paths["base"],
            [(reads.paths["vector"], cfg.alpha)],
            tmp / "model.safetensors",
            cfg.include,
            cfg.exclude,
            hashes=reads.hashes,
        )
        formula = {"formula": "base + alpha * vector", "alpha": cfg.alpha}
        record = workspace.api.register_file(
            merged,
            kind="checkpoint",
            name=call.step,
            config={**formula, **cfg.model_dump(), "cache_key": call.key},
            parents=[
                (inputs["base"], "base"),
                (inputs["vector"], "vector", {"alpha": cfg.alpha}),
                *selected_by(inputs),
            ],
            parent_hashes=reads.verified(),
            **provenance(),
        )
    return record.id


def _vector_roles(inputs: dict[str, str]) -> list[str]:
    """The roles `vector 0`, `vector 1`, … of a mean's inputs, in index order."""
    return sorted((r for r in inputs if r.startswith("vector ")), key=lambda r: int(r.split()[1]))


def _only_vectors(step: str, inputs: dict[str, str], config: dict[str, Any]) -> None:
    roles = _vector_roles(inputs)
    if len(roles) < 2 or len(roles) != len(inputs):
        raise ValueError(
            f"step {step!r}: a mean needs inputs 'vector 0', 'vector 1', … (2 or more), not {sorted(inputs)}"
        )


def _mean_vector(call: StepCall) -> str:
    """γ̄ = the mean of the input vectors `vector 0`, `vector 1`, … (their seed noise averages out: with a
    signal fraction ρ per draw, the mean of K points at the signal with cos √(Kρ / (Kρ + 1 − ρ)))."""
    workspace, inputs = call.workspace, call.inputs
    roles = _vector_roles(inputs)
    reads = workspace.stream({r: inputs[r] for r in roles})
    with workspace.scratch() as tmp:
        paths = [reads.paths[r] for r in roles]
        out = vector_ops.mean(paths, tmp / "vector.safetensors", hashes=reads.hashes)
        record = workspace.api.register_file(
            out,
            kind="vector",
            name=call.step,
            config={"formula": "mean of vectors", "count": len(roles), "cache_key": call.key},
            parents=[(inputs[r], "vector", {"index": i}) for i, r in enumerate(roles)],
            parent_hashes=reads.verified(),
            **provenance(),
        )
    return record.id


class NullVectorConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    seed: int = Field(0, description="seed of the random directions")


def _null_vector(call: StepCall) -> str:
    """A random vector with the per-tensor norms of input `vector` (the null-vector control)."""
    workspace, inputs, cfg = call.workspace, call.inputs, call.config
    reads = workspace.stream({"vector": inputs["vector"]})
    with workspace.scratch() as tmp:
        out = vector_ops.null_vector(
            reads.paths["vector"], tmp / "vector.safetensors", cfg.seed, hashes=reads.hashes
        )
        record = workspace.api.register_file(
            out,
            kind="vector",
            name=call.step,
            config={
                "formula": "random, with the per-tensor norms of vector",
                "seed": cfg.seed,
                "cache_key": call.key,
            },
            parents=[(inputs["vector"], "norms_from")],
            parent_hashes=reads.verified(),
            **provenance(),
        )
    return record.id


EXTRACT = StepKind("extract_vector", VectorFilter, ("minuend", "subtrahend"), _extract)
MERGE = StepKind("merge", MergeConfig, ("base", "vector"), _merge)
MEAN_VECTOR = StepKind("mean_vector", None, (), _mean_vector, check=_only_vectors)
NULL_VECTOR = StepKind("null_vector", NullVectorConfig, ("vector",), _null_vector)
run_extract = EXTRACT.run
run_merge = MERGE.run
run_mean_vector = MEAN_VECTOR.run
extract_task = step_task(EXTRACT)
merge_task = step_task(MERGE)
mean_vector_task = step_task(MEAN_VECTOR)
null_vector_task = step_task(NULL_VECTOR)
