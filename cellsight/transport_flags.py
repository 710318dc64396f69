"""The ``--mode/--connect/--listen/--config`` flags every process takes (zenoh-python ``common.py``).

A command decorated with ``transport_options`` gets the four flags and receives them as one
``transport: TransportFlags``; flags given on the command line override the ``[transport]``
section of the cell config.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

if TYPE_CHECKING:
    from schemas.bus import TransportConfig

ModeOpt = Annotated[
    str | None, typer.Option("--mode", help="zenoh mode: client, peer or router", rich_help_panel="Transport")
]
ConnectOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--connect",
        "-e",
        help="endpoint to connect to (repeatable), e.g. tcp/127.0.0.1:7447",
        rich_help_panel="Transport",
    ),
]
ListenOpt = Annotated[
    list[str] | None,
    typer.Option("--listen", "-l", help="endpoint to listen on (repeatable)", rich_help_panel="Transport"),
]
ZenohConfigOpt = Annotated[
    Path | None,
    typer.Option("--config", help="zenoh JSON5 config file (TLS, mTLS, access control)", rich_help_panel="Transport"),
]
CellOpt = Annotated[str | None, typer.Option("--cell", help="cell name (default: from the cell config, else 'demo')")]


@dataclass(frozen=True)
class TransportFlags:
    """The transport flags as given (None: not given)."""

    mode: str | None = None
    connect: list[str] | None = None
    listen: list[str] | None = None
    zenoh_config: Path | None = None

    def apply(self, base: TransportConfig | None) -> TransportConfig:
        """``base`` (from the cell config, or defaults) with the given flags on top."""
        from schemas.bus import TransportConfig  # lazy: keeps --help instant

        data = (base or TransportConfig()).model_dump()
        if self.mode is not None:
            data["mode"] = self.mode
        if self.connect:
            data["connect"] = list(self.connect)
        if self.listen:
            data["listen"] = list(self.listen)
        if self.zenoh_config is not None:
            data["zenoh_config"] = self.zenoh_config
        return TransportConfig.model_validate(data)


_FLAGS = (("mode", ModeOpt), ("connect", ConnectOpt), ("listen", ListenOpt), ("zenoh_config", ZenohConfigOpt))


def transport_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """Add the four transport flags to a typer command whose last parameter is
    ``transport: TransportFlags``; typer sees the flags, the command one object."""
    sig = inspect.signature(command, eval_str=True)
    kept = [p for name, p in sig.parameters.items() if name != "transport"]
    flags = [
        inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=None, annotation=ann) for name, ann in _FLAGS
    ]

    @functools.wraps(command)
    def with_flags(*args: Any, mode=None, connect=None, listen=None, zenoh_config=None, **kwargs: Any) -> Any:
        return command(*args, transport=TransportFlags(mode, connect, listen, zenoh_config), **kwargs)

    with_flags.__signature__ = sig.replace(parameters=kept + flags)  # type: ignore[attr-defined]
    return with_flags
