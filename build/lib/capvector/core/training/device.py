"""Device selection shared by training and evaluation."""

from __future__ import annotations

from typing import Any

import torch


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """ "auto" -> CUDA when available, else CPU; anything else is passed to torch.device (and checked)."""
    if isinstance(device, torch.device):
        return device
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except RuntimeError as exc:
        raise ValueError(f"unknown device {device!r}: use 'auto', 'cpu', 'cuda' or 'cuda:N'") from exc
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested but CUDA is not available here")
    return resolved


def device_label(device: torch.device) -> str:
    """`cpu`, or `cuda:N` with N filled in (a bare `cuda` is the current CUDA device)."""
    if device.type == "cuda" and device.index is None:
        return f"cuda:{torch.cuda.current_device()}"
    return str(device)


def run_environment(device: torch.device) -> dict[str, Any]:
    """Where a computation runs, for its provenance: the device (resolved: never `auto`), the GPU's
    name, torch's CPU thread count now, the torch build and whether CUDA was available."""
    label = device_label(device)
    return {
        "device": label,
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "num_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "cuda_available": torch.cuda.is_available(),
        "cuda_version": torch.version.cuda,
    }
