"""Batched rollouts on Meta-World under a fingerprinted protocol."""
