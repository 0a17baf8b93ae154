"""Command line of the AR drone simulator: track, evaluate, serve, loadtest, config."""

from __future__ import annotations

import logging
import sys
from typing import Annotated

import typer
from rich.markup import escape

from server import __version__
from server.cli.common import ConfigFile, ConfigSets, console, effective_config, err_console
from server.cli.offline import evaluate_cmd, track
from server.cli.online import loadtest, serve
from server.errors import DroneSimError

app = typer.Typer(no_args_is_help=True, help=__doc__, rich_markup_mode="markdown")


def _print_version(value: bool) -> None:
    if value:
        console.print(f"dronesim-ar {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_print_version, is_eager=True, help="print the version and exit"
        ),
    ] = False,
) -> None:
    # The group's help is the module's docstring (Typer(help=...)).
    pass


def config_cmd(config_file: ConfigFile = None, sets: ConfigSets = None) -> None:
    """Print the effective configuration as YAML (defaults < --config FILE < DRONESIM_*
    environment < --set), to edit and pass back with --config."""
    config = effective_config(config_file, sets)
    sys.stdout.write(config.to_yaml())


# The commands, in the order --help lists them: offline (offline.py), then around a running
# server (online.py), then the configuration.
app.command()(track)
app.command("evaluate")(evaluate_cmd)
app.command()(serve)
app.command()(loadtest)
app.command("config")(config_cmd)


def main() -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        app()
    except DroneSimError as exc:
        err_console.print(f"[red]error:[/red] {escape(str(exc))}")
        sys.exit(1)
