"""The ``cellsight`` command: the app, its groups and the exit-code table. The commands themselves
live in ``cellsight/commands/``, a module per group; they parse, call library code and print.
Errors become exit codes in one place, ``EXIT_CODES``, applied to every command by the top-level
group. Heavy imports happen inside the commands so that ``--help`` is instant.

Exit codes: 0 ok, 1 nothing received / a run or check failed, 2 bad configuration or input,
3 bus error.
"""

from __future__ import annotations

import click
import typer
from typer.core import TyperGroup

from cellsight.commands import bus, cell, config, files, logs, processes
from cellsight.commands.common import fail
from cellsight.errors import CellsightError, ConfigError, RunError
from drivers.errors import DriverError  # noqa: E402  (the packages' exception roots: small modules)
from estimator.errors import EstimatorError  # noqa: E402
from recognition.errors import RecognitionError  # noqa: E402
from schemas.errors import BusError, SchemaError  # noqa: E402

#: Exception -> exit code, first match wins: the one place errors become exit codes.
EXIT_CODES: tuple[tuple[type[BaseException], int], ...] = (
    (BusError, 3),  # the zenoh session could not be opened or used
    (RunError, 1),  # a cell or a recording could not run to the end
    (ConfigError, 2),
    (SchemaError, 2),  # bad keys, undecodable payloads or logs
    (DriverError, 2),  # no device, bad scenario or image
    (RecognitionError, 2),  # bad cloud, mesh or model database
    (EstimatorError, 2),
    (CellsightError, 1),
    (OSError, 2),  # a file that cannot be read or written
    (ValueError, 2),  # a flag value pydantic refused (e.g. --mode)
)


def exit_code(exc: BaseException) -> int | None:
    """The exit code ``EXIT_CODES`` gives an exception, None for one it does not know (a bug)."""
    return next((code for kind, code in EXIT_CODES if isinstance(exc, kind)), None)


class _Commands(TyperGroup):
    """The top-level group: runs the command and turns a known error into its message and exit code."""

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except click.exceptions.ClickException:
            raise
        except Exception as exc:
            code = exit_code(exc)
            if code is None:
                raise
            raise fail(str(exc), code) from None


app = typer.Typer(
    cls=_Commands, help="cellsight: self-aligning multi-camera work-cell monitoring.", no_args_is_help=True
)
app.add_typer(config.config_app, name="config")
app.add_typer(bus.bus_app, name="bus")
app.add_typer(config.security_app, name="security")
app.add_typer(processes.driver_app, name="driver")
app.add_typer(files.sim_app, name="sim")
app.add_typer(files.markers_app, name="markers")
app.add_typer(files.model_app, name="model")
app.add_typer(logs.export_app, name="export")
for _name, _command in (
    ("router", bus.router),
    ("estimator", processes.estimator_cmd),
    ("recognition", processes.recognition_cmd),
    ("recognize", files.recognize_cmd),
    ("record", cell.record),
    ("run", cell.run_cmd),
    ("demo", cell.demo),
    ("status", bus.status),
    ("replay", cell.replay_cmd),
    ("resolve", logs.resolve_cmd),
    ("compare", logs.compare_cmd),
):
    app.command(_name)(_command)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
