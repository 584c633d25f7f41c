"""Which capvector home a command works on: the one resolver for every `capvector` command.

In order: the command's own `--home`, then the `--home` given before the command (`capvector --home H
verify`, also read from $CAPVECTOR_HOME by capvector.flows.cli.main.main_options), then
capvector.artifacts.home.default_home
(./capvector_home). capvector.flows.cli.main records the root option here; the command modules ask
`resolve_home`.
"""

from __future__ import annotations

_root_home: str | None = None


def set_root_home(home: str | None) -> None:
    """The `--home` of the `capvector` command itself (None: not given), set once per invocation."""
    global _root_home
    _root_home = home


def resolve_home(home: str | None = None) -> str:
    """The home a command should open, given its own `--home` (or None)."""
    if home:
        return home
    if _root_home:
        return _root_home
    from capvector.artifacts.home import default_home

    return default_home()
