"""Checkpoints as safetensors and the capability-vector arithmetic on them."""
