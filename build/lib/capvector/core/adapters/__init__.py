"""Low-rank adapters: LoRA through peft, and rank-adaptive LoRA-SP."""
