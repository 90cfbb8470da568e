"""Entry point of the ``sekd`` command: a click group; each command lives in its own module."""
from __future__ import annotations

import logging
import sys

import click

from sekd_sfm import __version__
from sekd_sfm.errors import SekdError
from sekd_sfm.failures import debug_enabled, explain
from sekd_sfm.runtime import forget_handled_interrupt, stop_cleanly_on_sigterm


class SekdGroup(click.Group):
    """The one top-level handler: any failure below ends as one ``Error: ...`` line and exit code 1.

    SekdError carries its own message; OS errors (disk full, permission denied, ...), memory
    exhaustion and HDF5/torch errors from bad input get one from ``sekd_sfm.failures.explain``.
    ``SEKD_DEBUG=1`` shows the traceback instead. Ctrl-C is left to click ("Aborted!").
    """

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        ctx.meta["sekd.argv"] = list(args)  # kept to name the files an error message is about
        return super().parse_args(ctx, args)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except SekdError as exc:
            if debug_enabled():
                raise
            raise click.ClickException(str(exc)) from None
        except Exception as exc:  # the single place where every other failure becomes one line
            if debug_enabled():
                raise
            raise click.ClickException(explain(exc, inputs=ctx.meta.get("sekd.argv", []))) from None


@click.group(cls=SekdGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="sekd")
@click.option("-q", "--quiet", is_flag=True, help="Only print warnings and errors.")
def sekd(quiet: bool) -> None:
    """SEKD learned local features for 3D reconstruction.

    \b
    Data flows through the commands in this order:
      images -> extract -> features.h5 -> match -> matches.h5 -> reconstruct -> COLMAP model
    Every command resumes where an interrupted run stopped. Run `sekd COMMAND --help` for details.
    Failures print one `Error: ...` line (exit code 1); set SEKD_DEBUG=1 to get the traceback
    (and sekd's debug notes).
    """
    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO, format="%(message)s", stream=sys.stderr)
    if debug_enabled():
        logging.getLogger("sekd").setLevel(logging.DEBUG)
    stop_cleanly_on_sigterm()


def _register() -> None:
    from . import bench, doctor, export, extract, match, reconstruct

    sekd.add_command(extract.extract)
    sekd.add_command(doctor.doctor)
    sekd.add_command(bench.bench)
    sekd.add_command(match.pairs)
    sekd.add_command(match.match)
    sekd.add_command(reconstruct.reconstruct)
    sekd.add_command(reconstruct.relpose)
    sekd.add_command(export.export)
    from . import presets, show
    sekd.add_command(presets.confs)
    sekd.add_command(show.show)
    from . import train as train_commands
    sekd.add_command(train_commands.evolve); sekd.add_command(train_commands.train)
    from . import adapt as adapt_commands
    sekd.add_command(adapt_commands.adapt)
    from . import distill as distill_commands
    sekd.add_command(distill_commands.distill)
    from . import localize as localize_command
    sekd.add_command(localize_command.localize)
    from . import triangulate as triangulate_command
    sekd.add_command(triangulate_command.triangulate)


_register()


def main() -> None:
    try:
        sekd(prog_name="sekd")
    except KeyboardInterrupt:
        # click turns an interrupt during a command into one message and exit code 1; one that
        # arrives after that message (during exit) must not end the process by SIGINT instead.
        sys.exit(1)
    finally:
        forget_handled_interrupt()


if __name__ == "__main__":
    main()
