"""The steps: each reads its inputs by id, skips work already answered, registers what it makes."""
