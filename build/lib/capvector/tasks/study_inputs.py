"""What each input of a study's analysis is, as typed keys: the flow names an input with one of these
models and the analysis reads it back as the same model, never by splitting a string by hand. The
key's text (`test/<arm>/<draw>/<seed>/<budget>`, ...) is the input's role in the study artifact's
lineage, so it stays readable in `capvector lineage`."""

from __future__ import annotations

from typing import ClassVar, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError


class InputKey(BaseModel):
    """One kind of analysis input; its fields, in order, are the key's parts after the kind."""

    model_config = ConfigDict(frozen=True, extra="forbid")
    kind: ClassVar[str]

    @property
    def key(self) -> str:
        return "/".join([self.kind, *(str(getattr(self, name)) for name in type(self).model_fields)])

    @classmethod
    def parse(cls: type[K], key: str) -> K:
        names = list(cls.model_fields)
        parts = key.split("/", len(names))[1:]  # the last part may hold "/" (a selection's name)
        try:
            if len(parts) != len(names):
                raise ValueError(f"{len(parts)} parts")
            return cls(**dict(zip(names, parts, strict=True)))
        except (ValueError, ValidationError) as exc:
            shape = "/".join([cls.kind, *(f"<{n}>" for n in names)])
            why = exc if not isinstance(exc, ValidationError) else exc.errors()[0]
            if isinstance(why, dict):
                why = f"{why['loc'][0]}: {why['msg']}"
            raise ValueError(f"analysis input {key!r} is not {shape} ({why})") from None


K = TypeVar("K", bound=InputKey)


class TestEvaluation(InputKey):
    """A compared run's checkpoint at a budget (0: its start) on the test goals."""

    kind: ClassVar[str] = "test"
    arm: str
    draw: int
    seed: int
    budget: int


class ExtractionValidation(InputKey):
    """θ_pt, θ_ft^d, θ_ao^d or θ_meta^d on D_ext validation goals (preconditions b and d)."""

    kind: ClassVar[str] = "extval"
    which: str
    draw: int


class HeldOutLoss(InputKey):
    """An extraction run's held-out action loss at a budget (precondition a)."""

    kind: ClassVar[str] = "loss"
    which: str
    draw: int
    budget: int


class DownstreamLoss(InputKey):
    """A compared run's final held-out action loss on D_down (the continuous secondary endpoint)."""

    kind: ClassVar[str] = "downloss"
    arm: str
    draw: int
    seed: int


class CapabilityVector(InputKey):
    """γ^d (precondition e)."""

    kind: ClassVar[str] = "vector"
    draw: int


class ReplicateVector(InputKey):
    """γ̄^r, the mean of a replicate's draws (precondition e: do replicates agree?)."""

    kind: ClassVar[str] = "replicate"
    replicate: int


class StandardRun(InputKey):
    """θ_ft^d, whose differences between draws are the seed-noise vector (precondition e)."""

    kind: ClassVar[str] = "ft"
    draw: int


class Pretrained(InputKey):
    """θ_pt, the reference of cos(γ, θ_ft − θ_pt) (precondition e)."""

    kind: ClassVar[str] = "pt"


class Selection(InputKey):
    """A value chosen on validation goals."""

    kind: ClassVar[str] = "selection"
    name: str


KINDS = {
    k.kind: k
    for k in (
        TestEvaluation,
        ExtractionValidation,
        HeldOutLoss,
        DownstreamLoss,
        CapabilityVector,
        ReplicateVector,
        StandardRun,
        Pretrained,
        Selection,
    )
}


def inputs_of(inputs: dict[str, str], key_type: type[K]) -> list[tuple[K, str]]:
    """The inputs of one kind as (typed key, artifact id), in key order; a key of no known kind is an
    error naming it."""
    unknown = sorted(k for k in inputs if k.split("/")[0] not in KINDS)
    if unknown:
        raise ValueError(f"analysis inputs of no known kind: {unknown[:3]} (kinds: {sorted(KINDS)})")
    return [(key_type.parse(k), v) for k, v in sorted(inputs.items()) if k.split("/")[0] == key_type.kind]
