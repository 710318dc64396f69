"""``cellsight config`` and ``cellsight security``: cell configurations and the secure profile."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cellsight.commands.common import (
    load,
    stderr,
)
from cellsight.transport_flags import CellOpt

config_app = typer.Typer(help="Check and show cell configurations.", no_args_is_help=True)
security_app = typer.Typer(help="The secure deployment profile: mutual TLS and access control.", no_args_is_help=True)


@config_app.command("check")
def config_check(file: Annotated[Path, typer.Argument(help="cell config TOML")]) -> None:
    """Validate a cell config; print it with defaults filled in, or say what is wrong (exit 2)."""
    cfg = load(file)
    typer.echo(cfg.to_toml())
    stderr().print(f"[green]{file}: ok[/] ({len(cfg.cameras)} cameras, {len(cfg.estimator.anchors)} anchors)")


@config_app.command("show")
def config_show(
    file: Annotated[Path | None, typer.Argument(help="cell config TOML (default: built-in)")] = None,
) -> None:
    """Print the effective configuration (defaults + file + CELLSIGHT__* environment) as TOML."""
    typer.echo(load(file).to_toml())


@config_app.command("docs")
def config_docs() -> None:
    """Print every configuration section and field with its default, as Markdown (docs/configuration.md)."""
    from cellsight.config_docs import markdown

    typer.echo(markdown(), nl=False)


@security_app.command("init")
def security_init(
    directory: Annotated[Path, typer.Argument(help="new directory for the CA, certificates and zenoh configs")],
    cell: CellOpt = None,
    listen: Annotated[str, typer.Option("--listen", help="the router's TLS endpoint")] = "tls/127.0.0.1:7447",
    host: Annotated[
        list[str] | None,
        typer.Option(
            "--host", help="name or address clients reach the router by (repeatable; default 127.0.0.1 and localhost)"
        ),
    ] = None,
    ros2_domain: Annotated[
        int | None,
        typer.Option(
            "--ros2-domain",
            min=0,
            max=232,
            help="let this ROS 2 domain's rmw_zenoh traffic through ([ros2] enabled); default: none",
        ),
    ] = None,
) -> None:
    """Make a certificate authority, certificates for the router and each role, and their zenoh configs.

    Then: `cellsight router --config DIR/router.json5`, and each process with `--config DIR/ROLE.json5`
    (driver, estimator, recognition, recorder, viewer; a ROS 2 robot's zenoh router or node uses
    robot.pem / robot.key). Keep DIR/ca.key offline once done.
    """
    from schemas.security import EDGE_LISTEN, PUBLISH, PUBLISH_ROS2, write_profile

    profile = write_profile(
        directory, cell or "demo", listen, tuple(host) if host else ("127.0.0.1", "localhost"), ros2_domain
    )
    typer.echo(f"router:      cellsight router --config {profile.router_config}")
    for role, path in profile.role_configs.items():
        topics = PUBLISH[role] + (
            [f"ROS 2 {ros2_domain}/{t}" for t in PUBLISH_ROS2.get(role, [])] if ros2_domain is not None else []
        )
        typer.echo(
            f"{role + ':':12} --config {path}   publishes: {', '.join(topics) or 'nothing (subscribe and query only)'}"
        )
    typer.echo(
        f'edge host:   [cell] router_config = "{profile.edge_router_config}", its drivers --config {profile.role_configs["driver"]} '
        f"--connect {EDGE_LISTEN}   publishes: what a driver may"
    )
