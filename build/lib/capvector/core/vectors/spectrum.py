"""Spectra of weight updates: per 2-D tensor of an update B − A (or of a vector), its singular values and
how many directions hold most of its energy.

Why: an update that is low-rank (a few directions per matrix) changes far less of a policy than its norm
suggests, and which modules it touches that way (attention, MLP, encoders, action head) says where a
capability vector acts. The energy of a matrix is the sum of its squared singular values (its squared
Frobenius norm); the rank holding a fraction f of it is the smallest k whose k largest singular values
hold at least f of it, against the full rank min(rows, cols). An update of zeros holds no energy: its
ranks are 0.

Singular values are computed in float64 by LAPACK (numpy: no torch import), one tensor (of each input)
in memory at a time, so memory follows the largest tensor, not the checkpoint. Their last bits follow the
BLAS's thread count, so the same update measured with another count of threads may differ in those bits.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel

from capvector.core.vectors import module_patterns
from capvector.core.vectors.safetensors_io import Checkpoint, _few
from capvector.core.vectors.vector_ops import PathLike, VectorOpError, tensor_float64

ENERGY_FRACTIONS = (0.5, 0.9, 0.99)
# A cumulative energy this close below a fraction reaches it: equal singular values (5 of 10 hold 50 %)
# must not fall to the next rank by the last bit of an SVD.
TIE_TOLERANCE = 1e-12
# Module kinds by the tensor names of this project's policies (`capvector.core.policies`: token_backbone,
# l1_chunk, flow), first match wins, in the one pattern syntax (`module_patterns`); attention and MLP
# cover the backbone's blocks and the flow policy's action expert alike. The action head is the layer
# that writes actions and the expert's maps that read them (noisy actions, flow time). A name that
# matches none (language embedding, positions, token types, action queries) is "other".
MODULE_KINDS: dict[str, tuple[str, ...]] = {
    "attention": ("attn.*",),
    "mlp": ("mlp.*",),
    "encoder": ("state.*", "vision.*", "proprio.*"),
    "action_head": ("action_head.*", "action_expert.action_in.*", "action_expert.time_mlp_*"),
}
OTHER = "other"
KIND_ORDER = (*MODULE_KINDS, OTHER)


class TensorSpectrum(BaseModel):
    """The spectrum of one 2-D tensor: its singular values (largest first) and its energy ranks."""

    tensor: str
    kind: str  # one of KIND_ORDER
    rows: int
    cols: int
    full_rank: int  # min(rows, cols): the most directions the tensor can hold
    rank50: int
    rank90: int
    rank99: int
    top: float  # the largest singular value (the spectral norm)
    singular_values: list[float]


def module_kind(name: str) -> str:
    """The module kind a tensor belongs to, by its name (`MODULE_KINDS`); "other" when none fits."""
    found = (kind for kind, patterns in MODULE_KINDS.items() if module_patterns.matches_any(name, patterns))
    return next(found, OTHER)


def energy_rank(singular_values: np.ndarray, fraction: float) -> int:
    """The smallest k whose k largest singular values hold `fraction` of the energy (0 for no energy)."""
    energy = np.cumsum(np.square(np.asarray(singular_values, dtype=np.float64)))
    if energy.size == 0 or energy[-1] == 0:
        return 0
    return int(np.searchsorted(energy, fraction * energy[-1] * (1 - TIE_TOLERANCE))) + 1


def tensor_spectrum(name: str, matrix: np.ndarray) -> TensorSpectrum:
    """The spectrum of one finite 2-D float64 matrix."""
    values = np.linalg.svd(matrix, compute_uv=False)
    rank50, rank90, rank99 = (energy_rank(values, f) for f in ENERGY_FRACTIONS)
    rows, cols = matrix.shape
    return TensorSpectrum(
        tensor=name, kind=module_kind(name), rows=rows, cols=cols, full_rank=min(rows, cols),
        rank50=rank50, rank90=rank90, rank99=rank99, top=float(values[0]), singular_values=values.tolist(),
    )  # fmt: skip


def matrix_names(ckpt: Checkpoint) -> list[str]:
    """The tensors that have a spectrum: 2-D, float, not empty; in storage order (read sequentially)."""
    return [n for n, s in ckpt.specs.items() if s.is_float and len(s.shape) == 2 and min(s.shape) > 0]


def spectrum(vector: PathLike, subtrahend: PathLike | None = None) -> list[TensorSpectrum]:
    """The spectrum of each 2-D float tensor of `vector`, or of `vector − subtrahend` (B − A), which
    must hold each of them in the same shape. NaN or Inf is refused, naming the tensor."""
    ckpt = Checkpoint(vector)
    minus = Checkpoint(subtrahend) if subtrahend is not None else None
    names = matrix_names(ckpt)
    if not names:
        raise VectorOpError(f"{ckpt.path} has no 2-D float tensor: no spectrum to compute")
    if minus is not None:
        _check_subtrahend(names, ckpt, minus)
    return [tensor_spectrum(n, _update(n, ckpt, minus)) for n in names]


def _check_subtrahend(names: list[str], ckpt: Checkpoint, minus: Checkpoint) -> None:
    """Before any tensor is read: A must hold every matrix of B, in its shape."""
    missing = [n for n in names if n not in minus]
    if missing:
        raise VectorOpError(f"{len(missing)} tensor(s) missing from {minus.path}: {_few(missing)}")
    bad = [n for n in names if minus.specs[n].shape != ckpt.specs[n].shape]
    if bad:
        raise VectorOpError(f"{len(bad)} tensor(s) of {minus.path} differ in shape: {_few(bad)}")


def _update(name: str, ckpt: Checkpoint, minus: Checkpoint | None) -> np.ndarray:
    """Tensor `name` of B (less A's) in float64: the only tensor of the update in memory."""
    matrix = tensor_float64(ckpt, name)
    if minus is not None:
        with np.errstate(invalid="ignore"):  # Inf − Inf: refused just below, naming the tensor
            matrix -= tensor_float64(minus, name)
    if not np.isfinite(matrix).all():
        raise VectorOpError(f"NaN or Inf in tensor {name!r} of the update")
    return matrix
