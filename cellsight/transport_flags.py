"""The ``--mode/--connect/--listen/--config`` flags every process takes (zenoh-python ``common.py``).

Commands declare the four options with these annotated types and call ``transport_from_flags``;
flags given on the command line override the ``[transport]`` section of the cell config.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

if TYPE_CHECKING:
    from schemas.bus import TransportConfig

ModeOpt = Annotated[Optional[str], typer.Option("--mode", help="zenoh mode: client, peer or router", rich_help_panel="Transport")]
ConnectOpt = Annotated[Optional[list[str]], typer.Option("--connect", "-e", help="endpoint to connect to (repeatable), e.g. tcp/127.0.0.1:7447", rich_help_panel="Transport")]
ListenOpt = Annotated[Optional[list[str]], typer.Option("--listen", "-l", help="endpoint to listen on (repeatable)", rich_help_panel="Transport")]
ZenohConfigOpt = Annotated[Optional[Path], typer.Option("--config", help="zenoh JSON5 config file (TLS, mTLS, access control)", rich_help_panel="Transport")]
CellOpt = Annotated[Optional[str], typer.Option("--cell", help="cell name (default: from the cell config, else 'demo')")]


def transport_from_flags(
    base: "TransportConfig | None",
    mode: str | None,
    connect: list[str] | None,
    listen: list[str] | None,
    zenoh_config: Path | None,
) -> "TransportConfig":
    """``base`` (from the cell config, or defaults) with the given flags applied on top."""
    from schemas.bus import TransportConfig  # lazy: keeps --help instant

    data = (base or TransportConfig()).model_dump()
    if mode is not None:
        data["mode"] = mode
    if connect:
        data["connect"] = list(connect)
    if listen:
        data["listen"] = list(listen)
    if zenoh_config is not None:
        data["zenoh_config"] = zenoh_config
    return TransportConfig.model_validate(data)
