"""psdcal command line: a thin layer over the library.

Each command group lives in its own module of this package and registers
itself on :data:`cli`; heavy imports happen inside the commands, after the
arguments are parsed.  Every :class:`psdcal.errors.PsdcalError` becomes one
line on stderr and exit status 2.
"""
from __future__ import annotations

import sys

import click

from psdcal.errors import PsdcalError


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="psdcal")
def cli():
    """psdcal: model, calibrate and use PSD + lens angle-of-arrival sensors.

    Files are CSV in millimetres (docs/model.md#file-formats); a
    calibration is a JSON file.  Run `psdcal COMMAND --help` for details.
    """


# Command modules: each one adds its commands to `cli` when imported.
_COMMANDS = (
    "system_cmd",
    "calibrate_cmd",
    "simulate_cmd",
    "signal_cmd",
    "locate_cmd",
    "report_cmd",
    "reproduce_cmd",
    "directions_cmd",
    "inspect_cmd",
    "module_cmd",
    "gains_cmd",
    "export_cmd",
    "capture_cmd",
)


def _register() -> None:
    import importlib

    for name in _COMMANDS:
        try:
            importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:  # a module not written yet
            if exc.name != f"{__name__}.{name}":
                raise


def main(argv=None) -> int:
    """Entry point of the ``psdcal`` script; returns the exit status."""
    _register()
    try:
        cli.main(args=argv, standalone_mode=False, prog_name="psdcal")
    except click.exceptions.Abort:
        click.echo("psdcal: aborted", err=True)
        return 130
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    except PsdcalError as exc:
        msg = " ".join(str(exc).split())
        click.echo(f"psdcal: error: {msg}", err=True)
        return 2
    except KeyboardInterrupt:
        click.echo("psdcal: interrupted", err=True)
        return 130
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
