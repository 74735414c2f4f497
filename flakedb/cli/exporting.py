"""The body every ``flakedb export-*`` command shares (output directory checked before work, the export
registry's route run, one-line errors, nothing left behind): :func:`run_export`.

A file that is not a BSDF is bad input, and the output directories the run would have made are gone:

>>> import tempfile
>>> d = Path(tempfile.mkdtemp())
>>> _ = (d / "paint.bsdf").write_bytes(b"not a bsdf")
>>> try:
...     run_export(d / "paint.bsdf", d / "new" / "out", "openpbr", None, quiet=True)
... except FlakedbError as e:
...     print(e.exit_code, (d / "new").exists())
2 False
"""

from pathlib import Path

import click

from flakedb.bsdf import BSDFFileError
from flakedb.cli.errors import FlakedbError
from flakedb.cli.failures import probe_writable, remove_created_dirs
from flakedb.export.registry import export
from flakedb.outputs import OutputError, check_output_dir


def run_export(file, out, method, name, quiet, bad_input=(), **options):
    """The body every ``flakedb export-*`` command shares: the output directory (``--out``, else FILE's)
    checked and probed before any work, :func:`flakedb.export.registry.export` run with ``method``
    (progress on stderr unless ``quiet``), directories it created removed if it fails; a file that is not
    a BSDF, an output error or an exception class in ``bad_input`` becomes one line, exit status 2;
    ``options`` go to the route.  Returns the export's summary."""
    out_dir = Path(out) if out is not None else Path(file).absolute().parent
    try:
        check_output_dir(out_dir.absolute())
        probe_writable(out_dir.absolute())
    except OutputError as e:
        raise FlakedbError(str(e)) from None
    try:
        with remove_created_dirs(out_dir.absolute()):
            return export(file, out_dir, method=method, name=name,
                          progress=None if quiet else (lambda m: click.echo(m, err=True)), **options)
    except (BSDFFileError, OutputError, *bad_input) as e:
        raise FlakedbError(str(e)) from None
