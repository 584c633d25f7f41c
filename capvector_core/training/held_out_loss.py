"""A checkpoint's action loss on held-out demonstrations: the extraction runs' convergence check.

The loss is the policy's own training loss (its `compute_loss`), averaged over every sample in index
order with torch seeded, so a stochastic loss (flow matching's noise and times) gives the same number
for the same checkpoint. Pure torch, so a lent GPU machine without the workflow stack can run it too.
"""

from __future__ import annotations

from typing import Any

import torch

from capvector.core.policies.base import Policy, load_policy
from capvector.core.simulation.demos import DemoDataset


@torch.no_grad()
def held_out_action_loss(
    checkpoint: Any, dataset: DemoDataset, batch_size: int, seed: int, device: str = "cpu"
) -> float:
    """Mean of the policy's loss over every sample of `dataset` (batches in index order). `checkpoint`:
    a dense checkpoint's path, or a loaded policy (a LoRA-SP checkpoint as trained: init + adapter)."""
    policy = checkpoint if isinstance(checkpoint, Policy) else load_policy(checkpoint, device=device)
    policy.eval()
    torch.manual_seed(seed)
    n, make_batch = policy.make_batcher(dataset, policy.device)
    total = 0.0
    for start in range(0, n, batch_size):
        index = torch.arange(start, min(n, start + batch_size))
        terms = policy.compute_loss(make_batch(index)).terms
        total += float(torch.stack(list(terms.values())).sum()) * len(index)
    return total / n
