"""What every step runs on: the cache, the Prefect task decorator, code hashes, progress, scratch."""
