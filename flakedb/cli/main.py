"""flakedb's command line (click): the group and its registration.

Each command lives in its own module of ``flakedb/cli/`` (one module per command) and is registered
below; the user-facing error type is :class:`flakedb.cli.errors.FlakedbError`.
"""

import importlib
import signal

import click

from flakedb import __version__
from flakedb.cli.errors import FlakedbError  # noqa: F401  (re-exported for scripts)
from flakedb.cli.failures import as_failure, shorten_tokens
from flakedb.process import (
    blas_one_thread,
    environment_problems,
    exit_after_signal,
    fast_exit,
    install_signal_handlers,
    install_warning_format,
    received_signal,
    received_signal_since,
    signals_received,
    signal_exit_status,
    tune_allocator,
)

#: Every command and the module that defines it, imported only when that command runs or its help is
#: shown (click's lazily loaded subcommands): ``flakedb compose`` no longer imports Dask, distributed,
#: matplotlib and the build pipeline of ``flakedb build`` (measured: 1.2 s of imports for any command
#: before, docs/store.md "Timings").
COMMANDS = {
    "build": "flakedb.cli.build:build",
    "calibrate": "flakedb.cli.calibrate:calibrate",
    "compare": "flakedb.cli.compare:compare",
    "compose": "flakedb.cli.compose:compose",
    "demo": "flakedb.cli.demo:demo",
    "export-mitsuba": "flakedb.cli.export_mitsuba:export_mitsuba",
    "export-openpbr": "flakedb.cli.export_openpbr:export_openpbr",
    "export-cpa": "flakedb.cli.export_cpa:export_cpa",
    "info": "flakedb.cli.info:info",
    "match": "flakedb.cli.match:match",
    "render": "flakedb.cli.render:render",
    "report": "flakedb.cli.report:report",
    "species": "flakedb.cli.species:species",
    "texture": "flakedb.cli.texture:texture",
    "verify": "flakedb.cli.build:verify",
}

#: The one-line help of each command as ``flakedb --help`` lists it, so that listing imports no command
#: module (numpy alone is 0.15 s; every module together 1.4 s).  ``tests/cli/test_cli.py`` checks that each
#: entry is the command's own untruncated ``short_help`` (click's first-sentence summary of its docstring); a command
#: missing here is imported to get it.
SHORT_HELP = {
    'build': 'Build (or reuse) the projected-kernel store and point `latest` at it.',
    'calibrate': 'Calibrate a catalogue species from a masstone / let-down ladder (LADDER: a manifest YAML).',
    'compare': "Predict each RECIPE's colour at the target's geometries and compare: dL*, dC*, dH*, ΔE, pass/fail.",
    'compose': 'Compose the paint of RECIPE (YAML, schemas/recipe.schema.json) into a BSDF and a colour report.',
    'demo': 'Run the end-to-end demo with what flakedb can do today.',
    'export-mitsuba': "Export a Fourier .bsdf / flakedb .h5 FILE to Mitsuba 3's `measured` format (front-side reflection only).",
    'export-openpbr': 'Fit an OpenPBR Surface (coat, base colour, metalness, roughness) to a Fourier .bsdf / flakedb .h5 FILE by weighted least squares, and write NAME.mtlx (MaterialX), NAME.usda (USD), NAME.gltf / NAME.glb (glTF sphere) and NAME.blender.py (Principled BSDF).',
    'export-cpa': 'Fit a coat mirror, a Lambert term, three GGX lobes and a backscatter lobe whose colours are a table indexed by the view angle to a Fourier .bsdf / flakedb .h5 FILE, and write NAME.cpa.png (the table), NAME.cpa.mtlx (MaterialX standard nodes), NAME.cpa.blender.py (Cycles / EEVEE node group) and NAME.cpa.json (the fit and its ΔE00).',
    'info': "Describe a Fourier .bsdf, a flakedb .h5 or a Mitsuba 3 `measured` export: what paint, which channels and colour space, the smooth coat's mirror term, energy / colour / convergence checks in words, and the albedo at a few incident angles.",
    'match': 'Fit the {fit: [min, max]} fields of BASE (a recipe YAML) so its colour matches the target.',
    'render': 'Render unit spheres of the BSDFs in FILES (.bsdf, or a flakedb .h5 — a spectral one is converted to linear sRGB by the colour module) under a studio.',
    'report': 'Write a one-page QC report of RECIPE against the target: a PDF and a PNG of the same page.',
    'species': "The particle catalogue (catalog/particles.yaml) and each species' optics.",
    'texture': "Predicted sparkle (glints per mm², area fraction, intensity, contrast) and graininess of RECIPE, relative to the composed paint (compose's report section, identical), or with --flakes-only to the flakes.",
    'verify': "Check a store: completeness, schema, every chunk's sha256.",
}


def _truncate(text, limit) -> str:
    """``text`` cut at a word boundary to at most ``limit`` characters, with "..." (as click lists commands)."""
    if len(text) <= limit:
        return text
    cut = text[:max(limit - 3, 0)].rsplit(" ", 1)[0]
    return cut + "..."


def short_help(ctx, name) -> str:
    """The listed help of command ``name``: :data:`SHORT_HELP`, else the imported command's own."""
    if name in SHORT_HELP:
        return SHORT_HELP[name]
    cmd = ctx.command.get_command(ctx, name)
    return "" if cmd is None else cmd.get_short_help_str(limit=10**6)


class FlakedbGroup(click.Group):
    """The group: commands loaded on first use (:data:`COMMANDS`); an unexpected exception in a command
    becomes one line and exit status 1 (:func:`flakedb.cli.failures.as_failure`) unless ``--debug``
    asks for the traceback.

    >>> from click.testing import CliRunner
    >>> listing = CliRunner().invoke(cli, ["--help"]).output
    >>> [name for name in COMMANDS if f"  {name} " not in listing]                    # every command is listed
    []
    >>> result = CliRunner().invoke(cli, ["compse"])
    >>> result.exit_code, result.output.splitlines()[-1]
    (2, "Error: No such command 'compse'.")
    """

    def list_commands(self, ctx):
        return sorted(COMMANDS)

    def format_commands(self, ctx, formatter):
        """The command list of ``--help`` from :data:`SHORT_HELP`, importing no command module."""
        names = self.list_commands(ctx)
        limit = formatter.width - 6 - max(map(len, names), default=0)  # click's own layout
        rows = [(name, _truncate(short_help(ctx, name), limit)) for name in names]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)

    def get_command(self, ctx, name):
        target = COMMANDS.get(name)
        if target is None:
            return None
        module, attr = target.split(":")
        return getattr(importlib.import_module(module), attr)

    def invoke(self, ctx):
        problems = environment_problems()   # before any command's work (flakedb.process)
        if problems:
            raise FlakedbError("; ".join(problems))
        signals_before = signals_received()
        try:
            return super().invoke(ctx)
        except click.exceptions.ClickException as exc:
            exc.message = shorten_tokens(exc.message)   # never a 900 kB name echoed back
            raise
        except (click.exceptions.Exit, click.exceptions.Abort, SystemExit):
            raise
        except BaseException as exc:
            # SIGTERM / SIGHUP / SIGINT (flakedb.process.Terminated), also when a compiled kernel reported it as
            # a SystemError: the command's clean-up has run; exit status 128 + the signal's number
            code = signal_exit_status(exc)
            if code is None and signals_received() > signals_before:
                # the signal's exception was raised inside C code that replaced it with its own error (numpy's
                # comparison reported "Cannot compare structured arrays" for a Terminated raised in a callback):
                # the run was still ended by the signal
                code = 128 + int(received_signal_since(signals_before))
            if code is not None:
                try:
                    name = signal.Signals(code - 128).name
                except ValueError:
                    name = f"signal {code - 128}"
                click.echo(f"flakedb: terminated by {name}; stopped, temporary files removed, no partial outputs "
                           f"left", err=True)
                raise SystemExit(code) from None
            if not isinstance(exc, Exception) or ctx.params.get("debug"):
                raise
            raise as_failure(exc) from exc


@click.group(cls=FlakedbGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="flakedb")
@click.option("--debug", is_flag=True, help="Show the traceback of an unexpected error instead of one line.")
def cli(debug):
    """flakedb: predict a car paint's BSDF from what is in it."""


def main():
    blas_one_thread()  # before numpy loads: the BLAS's own threads only compete with flakedb's (flakedb.process)
    tune_allocator()  # freed memory kept for reuse: page faults are most of a short solve's overhead
    install_signal_handlers()  # SIGTERM / SIGHUP clean up as SIGINT does (flakedb.process.Terminated)
    install_warning_format()  # a library's warning as one line, not a source line (flakedb.process)
    try:
        cli(prog_name="flakedb")
    except SystemExit as exc:
        signum = received_signal()
        if signum is not None:   # the clean-up has run; no teardown under running kernels (flakedb.process)
            exit_after_signal(128 + signum)
        fast_exit(exc.code)  # a finished compose skips the interpreter's teardown (flakedb.process)
        raise


if __name__ == "__main__":
    main()
