"""psdcal command line: a thin layer over the library.

Each command group lives in its own module of this package and registers
itself on :data:`cli`; the top-level group (:class:`LazyGroup`) imports a
command's module only when that command runs (``psdcal --help`` imports
none), and heavy imports happen inside the commands, after the arguments are
parsed.  Every :class:`psdcal.errors.PsdcalError` becomes one
line on stderr and exit status 2.
"""
from __future__ import annotations

import sys

import click

from psdcal.errors import PsdcalError

#: Parameters (by their Python name) that name files or folders a command writes.
OUTPUT_PARAMS = frozenset({"output", "out", "out_dir", "csv_path", "json_out", "points_out", "track_path", "into",
                           "record_path"})
#: Outputs updated in place (merged into): they may exist without --force.
MERGE_PARAMS = frozenset({"into"})
#: Files a command writes into its output folder, keyed by command name (an existing one needs --force).
DIR_FILES = {
    "simulate": ("template.csv", "points.csv", "truth.json"),
    "template": ("template.csv", "truth.json"),
    "room": ("sensors.json", "emitters.csv", "truth.json"),
    "reproduce": ("report.md",),
}
#: Commands whose output is their own scratch result and is replaced on every run (`psdcal demo`, run by
#: `python3 tasks.py demo` again and again); an input is still never overwritten.
REPLACING_COMMANDS = frozenset({"demo"})
#: Extensions an output must have where the writer's format is fixed: (command, param) -> suffixes.
OUTPUT_SUFFIXES = {
    ("errormap", "output"): (".png",),
    ("plan", "output"): (".png",),
    ("compare", "output"): (".png", ".svg", ".pdf"),
    ("report", "output"): (".html", ".htm"),
}


def _paths(value):
    if value is None:
        return []
    if isinstance(value, (tuple, list)):
        return [v for item in value for v in _paths(item)]
    return [value]


class PolicyCommand(click.Command):
    """A command that follows the output policy (docs/guide/files-and-errors.md).

    A command with an output gets ``--force``; before its body runs, outputs
    that are inputs, exist (without --force), are folders, lie in a file or an
    unwritable folder, or have the wrong extension are refused in one line.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._policy = any(p.name in OUTPUT_PARAMS for p in self.params)
        if self._policy and not any(p.name == "force" for p in self.params):
            self.params.append(click.Option(["--force"], is_flag=True, default=False,
                                            help="Replace existing output files (an input is never overwritten)."))
            self._added_force = True
        else:
            self._added_force = False

    def make_parser(self, ctx):
        """click's parser, where a short option (``-t``) skips the long-option look-up's spelling suggestions.

        click tries every argument as a long option first; for ``-t`` that
        fails, builds "did you mean" suggestions (loading difflib), discards
        them and reads the short option. Here that first try fails without
        suggestions; a mistyped long option (``--templat``) still gets them.
        """
        parser = super().make_parser(ctx)
        match = getattr(parser, "_match_long_opt", None)
        longs, prefixes = getattr(parser, "_long_opt", None), getattr(parser, "_opt_prefixes", None)
        if match is None or longs is None or prefixes is None:  # another click: as it is
            return parser

        def match_long_opt(opt, explicit_value, state):
            if opt not in longs and opt[:2] not in prefixes:  # "-t": the parser reads it as a short option next
                raise click.NoSuchOption(opt, ctx=ctx)
            return match(opt, explicit_value, state)

        parser._match_long_opt = match_long_opt
        return parser

    def invoke(self, ctx):
        _check_values(ctx)
        if self._policy:
            force = ctx.params.pop("force", False) if self._added_force else bool(ctx.params.get("force"))
            self._guard(ctx, force or self.name in REPLACING_COMMANDS)
        return super().invoke(ctx)

    def _guard(self, ctx, force):
        from pathlib import Path

        from psdcal._atomic import guard_outputs

        ins, outs, dirs = [], [], []
        for p in self.params:
            if isinstance(p, click.Option | click.Argument) and not isinstance(p.type, click.Path):
                # live sources given as text: 'file:PATH' reads a file (or a named pipe), an input like any other
                for v in _paths(ctx.params.get(p.name)):
                    if isinstance(v, str) and v.startswith("file:") and len(v) > 5:
                        ins.append((p.human_readable_name, Path(v[5:])))
            if not isinstance(p, click.Option | click.Argument) or not isinstance(p.type, click.Path):
                continue
            opt = p.opts[-1] if isinstance(p, click.Option) else p.human_readable_name
            if isinstance(p, click.Option):
                longs = [o for o in p.opts if o.startswith("--")]
                opt = longs[0] if longs else p.opts[0]
            for v in _paths(ctx.params.get(p.name)):
                if not isinstance(v, (str, Path)) or str(v) == "-" or "://" in str(v):
                    continue
                if p.name in OUTPUT_PARAMS:
                    if not p.type.file_okay:
                        dirs.append((opt, Path(v)))
                        for n in DIR_FILES.get(self.name, ()):
                            outs.append((opt, Path(v) / n))
                    else:
                        outs.append((opt, Path(v)))
                else:
                    ins.append((opt, Path(v)))
        suffixes = {opt: sfx for (cmd, name), sfx in OUTPUT_SUFFIXES.items() if cmd == self.name
                    for p in self.params if p.name == name for opt in [
                        ([o for o in p.opts if o.startswith("--")] or p.opts)[0]]}
        merge = {([o for o in p.opts if o.startswith("--")] or p.opts)[0] for p in self.params if p.name in MERGE_PARAMS}
        guard_outputs(ins, outs, force, suffixes=suffixes, dirs=dirs, merge=merge)


#: Options that must be >= 0 / >= 1 wherever a command has them (by Python name).
NON_NEGATIVE = frozenset({"seed", "sigma_d_mm", "noise_mm", "noise_um", "min_snr", "gap_s"})
AT_LEAST_ONE = frozenset({"n_emitters", "images", "views", "trials", "grid", "workers", "chunk_samples"})
#: Options written into CSV cells: no separator, quote or line break.
CSV_CELL = frozenset({"image_id", "name"})


def _check_values(ctx) -> None:
    """Refuse NaN/infinite numbers, negative seeds and sigmas, zero counts, CSV-breaking ids (one line, exit 2)."""
    import math

    def fail(param, msg):
        raise click.BadParameter(msg, ctx=ctx, param=param)

    for p in ctx.command.params:
        v = ctx.params.get(p.name)
        if v is None or isinstance(v, bool):
            continue
        vals = v if isinstance(v, (tuple, list)) else (v,)
        flat = [x for item in vals for x in (item if isinstance(item, (tuple, list)) else (item,))]
        for x in flat:
            if isinstance(x, float) and not math.isfinite(x):
                fail(p, f"{x} is not a finite number")
            if isinstance(x, (int, float)) and not isinstance(x, bool):
                if p.name in NON_NEGATIVE and x < 0:
                    fail(p, f"{x} is negative")
                if p.name in AT_LEAST_ONE and x < 1:
                    fail(p, f"{x} must be at least 1")
            if p.name in CSV_CELL and isinstance(x, str) and any(c in x for c in ',"\r\n\t\x00'):
                fail(p, f"{x!r} contains a comma, quote, tab or line break (it becomes a CSV cell)")
        if p.name == "sensor_mm" and v is not None and any(x <= 0 for x in flat if isinstance(x, float)):
            fail(p, "sensor lengths must be positive")


class PolicyGroup(click.Group):
    """A group whose commands and subgroups follow the output policy."""

    command_class = PolicyCommand


PolicyGroup.group_class = PolicyGroup

#: Top-level commands: name -> (module of this package that defines it, first paragraph of its help).
#: ``psdcal --help`` lists them from here without importing a command module; ``psdcal NAME``
#: imports only NAME's module. tests/test_startup.py checks this table against the commands.
LAZY_COMMANDS = {
    'amplitudes': ('locate_cmd',
        'Demodulate RECORDING to carrier amplitudes (no calibration needed).'),
    'aoa': ('locate_cmd',
        'Convert impact points (x_mm,y_mm) or amplitudes (vx1..vy2) in POINTS.csv to angles.'),
    'bundle': ('system_cmd',
        'Calibrate several sensors together: all poses and emitter positions in one bundle adjustment.'),
    'calibrate': ('calibrate_cmd',
        'Calibrate a PSD + lens sensor from views of a planar LED template.'),
    'calibrate-directions': ('directions_cmd',
        'Calibrate a PSD + lens sensor from spots at known directions (rotation stage, goniometer).'),
    'compare': ('report_cmd',
        'Compare two calibrations of one sensor in angle of arrival over the field of view.'),
    'dashboard': ('dashboard_cmd',
        'Show the room in a browser: sensors, emitters with their 3-sigma, tracks, health and warnings.'),
    'demo': ('simulate_cmd',
        'Calibrate the bundled default data and show the truth beside the estimate.'),
    'errormap': ('locate_cmd',
        "Draw the AoA and position error over the field of view (the paper's Figure 9)."),
    'export': ('export_cmd',
        'Export a calibration for other tools.'),
    'gains': ('gains_cmd',
        'Fit the three relative channel gains from spots at known positions (bench, lens removed).'),
    'inspect': ('inspect_cmd',
        'Show what RECORDING holds: channels, carriers found, TDM segments.'),
    'locate': ('locate_cmd',
        'Demodulate RECORDING(s) and write angles of arrival and positions.'),
    'module': ('module_cmd',
        'Split a module RECORDING (X, Y, SUM of time-multiplexed LEDs) into LEDs.'),
    'next-view': ('capture_cmd',
        'Suggest the next calibration view: the template pose that lowers the worst AoA uncertainty most.'),
    'plan': ('system_cmd',
        'Plan an installation: coverage and position uncertainty over a plane of the room.'),
    'pose': ('system_cmd',
        "Estimate a calibrated sensor's rotation and position in the room (PnP + maximum likelihood)."),
    'record': ('live_cmd',
        'Record live SOURCES (one per sensor) with their arrival times, for `locate --replay`.'),
    'report': ('report_cmd',
        'Write the calibration report: one self-contained HTML page.'),
    'reproduce': ('reproduce_cmd',
        "Regenerate the paper's Tables 1-10 and Figure 9 beside the paper's numbers."),
    'selfcal': ('selfcal_cmd',
        "Calibrate the room: every sensor's pose from a tag waved through it."),
    'signal-noise': ('signal_cmd',
        'Measured std of the impact point (mm) per SNR, beside the first-order prediction.'),
    'simulate': ('simulate_cmd',
        'Simulate a calibration set (geometry only) with known truth.'),
    'simulate-recording': ('simrec_cmd',
        'Simulate four-channel recordings with known truth (template views, or a room).'),
    'tag-pose': ('selfcal_cmd',
        "The rigid tag's six-degree-of-freedom pose at every time step."),
    'track': ('system_cmd',
        'Filter a `locate` output (LOCATED.csv) per emitter with a constant-velocity Kalman filter.'),
}


class LazyGroup(PolicyGroup):
    """The top-level group: a command's module is imported when that command is looked up.

    The help's command listing uses :data:`LAZY_COMMANDS` (the short help is made from
    the first paragraph exactly as click makes it from the whole help), so that
    ``psdcal --help`` imports no command module.
    """

    def list_commands(self, ctx):
        return sorted(set(self.commands) | set(LAZY_COMMANDS))

    def get_command(self, ctx, cmd_name):
        if cmd_name not in self.commands and cmd_name in LAZY_COMMANDS:
            import importlib

            importlib.import_module(f"{__name__}.{LAZY_COMMANDS[cmd_name][0]}")
        return self.commands.get(cmd_name)

    def resolve_command(self, ctx, args):
        try:
            return super().resolve_command(ctx, args)
        except click.UsageError as exc:  # click >= 8.4 suggests from the loaded commands: from all of them
            no_such = getattr(click.exceptions, "NoSuchCommand", None)
            if no_such is None or not isinstance(exc, no_such) or exc.possibilities:
                raise
            raise no_such(exc.command_name, possibilities=self.list_commands(ctx), ctx=exc.ctx) from None

    def listed_command(self, name):
        """The command ``name`` if its module is loaded, else a stand-in with its short help (no import)."""
        cmd = self.commands.get(name)
        if cmd is None and name in LAZY_COMMANDS:
            cmd = click.Command(name, help=LAZY_COMMANDS[name][1])
        return cmd

    def format_commands(self, ctx, formatter):
        # click.Group.format_commands, with the stand-ins instead of importing every command
        commands = [(n, c) for n in self.list_commands(ctx) for c in [self.listed_command(n)]
                    if c is not None and not c.hidden]
        if commands:
            limit = formatter.width - 6 - max(len(n) for n, _ in commands)
            rows = [(n, c.get_short_help_str(limit)) for n, c in commands]
            from gettext import gettext as _  # as click words its section titles

            with formatter.section(_("Commands")):
                formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="psdcal")
@click.option("--events", type=click.Path(dir_okay=False), envvar="PSDCAL_EVENTS", default=None,
              help="Also append every warning line the command prints to this JSON-lines log "
                   "(read by `psdcal dashboard --events`); default: $PSDCAL_EVENTS.")
@click.pass_context
def cli(ctx, events):
    """psdcal: model, calibrate and use PSD + lens angle-of-arrival sensors.

    Files are CSV in millimetres (docs/model.md#file-formats); a
    calibration is a JSON file.  Run `psdcal COMMAND --help` for details.
    """
    if events:
        from psdcal.cli._events import logging_warnings

        ctx.with_resource(logging_warnings(events, ctx.invoked_subcommand or ""))


# Command modules: each one adds its commands to `cli` when imported (all of them: _register;
# one command's: LazyGroup.get_command).
_COMMANDS = tuple(dict.fromkeys(module for module, _ in LAZY_COMMANDS.values()))


def _register() -> None:
    """Import every command module (for code that walks ``cli.commands``; ``main`` imports lazily)."""
    import importlib

    for name in _COMMANDS:
        try:
            importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:  # a module not written yet
            if exc.name != f"{__name__}.{name}":
                raise


def _one_line(msg) -> str:
    return " ".join(str(msg).split())


def _error(msg) -> int:
    click.echo(f"psdcal: error: {_one_line(msg)}", err=True)
    return 2


def _quiet_libraries() -> None:
    """numpy floating-point warnings and npTDMS log lines must not come before the one error line."""
    import logging
    import warnings

    warnings.filterwarnings("ignore", category=RuntimeWarning, module="numpy")
    warnings.filterwarnings("ignore", message=".*(overflow|invalid value|divide by zero).*", category=RuntimeWarning)
    logging.getLogger("nptdms").setLevel(logging.CRITICAL)


def main(argv=None) -> int:
    """Entry point of the ``psdcal`` script; returns the exit status.

    Every error a user can cause prints ONE line ``psdcal: error: ...`` on
    stderr and exits 2; the outputs of a command are written as one set
    (:func:`psdcal._atomic.output_set`), so a failed command changes nothing.
    """
    from psdcal._atomic import output_set

    import logging

    _quiet_libraries()
    logging.disable(logging.WARNING)  # npTDMS and friends: no log line before the one error line
    try:
        with output_set():
            cli.main(args=argv, standalone_mode=False, prog_name="psdcal")
    except click.exceptions.Abort:
        click.echo("psdcal: aborted", err=True)
        return 130
    except click.exceptions.NoArgsIsHelpError as exc:  # pragma: no cover - click >= 8.2
        click.echo(exc.format_message(), err=True)
        return 2
    except click.UsageError as exc:
        hint = f" (see 'psdcal {exc.ctx.command_path.split(' ', 1)[1]} --help')" if exc.ctx is not None and " " in exc.ctx.command_path else ""
        return _error(f"{exc.format_message()}{hint}")
    except click.ClickException as exc:
        _error(exc.format_message())
        # a psdcal command's own status is kept (`inspect`: 1, a carrier is off); click's own errors exit 2
        return exc.exit_code if type(exc).__module__.startswith("psdcal.") else 2
    except PsdcalError as exc:
        return _error(exc)
    except KeyboardInterrupt:
        click.echo("psdcal: interrupted", err=True)
        return 130
    except MemoryError:
        return _error("out of memory: the input or the options ask for more than this machine has")
    except OSError as exc:
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        return _error(f"{where}{exc.strerror or exc}")
    except RecursionError:
        return _error("input nested too deeply")
    except UnicodeDecodeError as exc:
        return _error(f"an input file is not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}); "
                      "save it as UTF-8")
    finally:
        logging.disable(logging.NOTSET)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
