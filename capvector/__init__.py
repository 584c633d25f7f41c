"""capvector: capability vectors for vision-language-action policies.

Installed, every part of the project lives under this one name: `capvector.core` (the library: Meta-World,
policies, training, evaluation, vector arithmetic), `capvector.stats` (a study's statistics),
`capvector.artifacts` (the store and the DuckDB catalogue), `capvector.tasks` (cached steps) and
`capvector.flows` (flows and the `capvector` command line). Importing this package imports none of them.
"""
