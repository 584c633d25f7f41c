"""The recipe's settings (a pipeline preset's), a downstream arm's submission, and old reports' reader;
running it (`run`, `sweep`) is a study's (capvector.flows.study)."""
