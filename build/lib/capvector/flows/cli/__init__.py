"""The `capvector` command line: one module per command group, and the options they share."""
