"""How a command fails: one line, an exit status, nothing left behind (issue 13).

* :class:`FlakedbFailure`: an error that is not the input's fault (disk full, a store that cannot be
  written, a worker that died): one line, exit status 1.  Bad input is
  :class:`flakedb.cli.errors.FlakedbError` (exit status 2).
* :func:`as_failure`: any other exception as a one-line :class:`FlakedbFailure` naming what failed
  and what to do; the group in :mod:`flakedb.cli.main` applies it unless ``--debug`` is given.
* :func:`remove_created_dirs`: a context manager that removes the directories a command created
  for its outputs when the command fails and they are still empty.
* :func:`check_plan`: a command's output plan checked before any work (issue 25), stale temporary
  entries of killed runs removed and reported.
"""

from __future__ import annotations

import contextlib
import errno
import re
import sys
import tempfile
from pathlib import Path

import click

from flakedb.outputs import OutputError, sweep_stale
from flakedb.store.errors import StoreError

#: Longest message kept on the one line (a longer one is cut, its start kept).
MAX_MESSAGE_CHARS = 500


def _is_loaded_instance(exc, module, name) -> bool:
    """``isinstance(exc, module.name)`` without importing ``module``: an exception of a class whose module
    was never imported cannot exist (so ``flakedb --help`` does not import the BSDF package and numpy)."""
    mod = sys.modules.get(module)
    return mod is not None and isinstance(exc, getattr(mod, name))


class FlakedbFailure(click.ClickException):
    """A failure that is not bad input: printed as one line without a traceback, exit status 1."""

    exit_code = 1


#: Longest run of characters without a space kept in a message (a name, a value, a path); a longer one is cut.
MAX_TOKEN_CHARS = 200


def shorten_tokens(text, limit=MAX_TOKEN_CHARS) -> str:
    """``text`` with every run of more than ``limit`` characters without white space cut to its start, with how
    long it was: a message never echoes a 900 kB species name or value.

    >>> shorten_tokens("unknown species 'x" + "y" * 900_000 + "'", limit=10)
    "unknown species 'xyyyyyyyy... (900,003 characters)"
    """
    if len(text) <= limit:
        return text
    return re.sub(r"\S{%d,}" % (limit + 1), lambda m: f"{m.group(0)[:limit]}... ({len(m.group(0)):,} characters)",
                  text)


def _one_line(text) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= MAX_MESSAGE_CHARS else text[:MAX_MESSAGE_CHARS - 3] + "..."


_OS_HINTS = {
    errno.ENOSPC: "free some space, then rerun the command (finished work is kept)",
    errno.EDQUOT: "free some space, then rerun the command (finished work is kept)",
    errno.EACCES: "choose a location you can write, or fix its permissions",
    errno.EPERM: "choose a location you can write, or fix its permissions",
    errno.EROFS: "the file system is read-only; choose a writable location",
    errno.EISDIR: "a directory is where a file should be; remove or rename it",
    errno.ENOTDIR: "a file is where a directory should be; remove or rename it",
    errno.ENOENT: "check the path",
}


def as_failure(exc: BaseException) -> click.ClickException:
    """A one-line ClickException for ``exc`` (exit status 1; 2 for a BSDF file that cannot be read).

    An operating-system error becomes one line with a hint; anything unexpected says how to get the
    traceback:

    >>> err = as_failure(OSError(errno.ENOSPC, "No space left on device", "/data/out/paint.h5"))
    >>> err.exit_code, err.message
    (1, '/data/out/paint.h5: No space left on device (hint: free some space, then rerun the command (finished work is kept))')
    >>> as_failure(KeyError("x")).message
    "internal error: KeyError: 'x' (hint: rerun with `flakedb --debug ...` for the traceback and report it)"
    """
    if isinstance(exc, OSError):
        where = f"{exc.filename}: " if exc.filename else ""
        what = exc.strerror or type(exc).__name__
        hint = _OS_HINTS.get(exc.errno)
        return FlakedbFailure(_one_line(f"{where}{what}" + (f" (hint: {hint})" if hint else "")))
    if isinstance(exc, MemoryError):
        return FlakedbFailure("out of memory (hint: memory grows with the node count (--n or the recipe's "
                              "resolution), the number of bands (spectral.step_nm), a pigment's median_diameter_um and "
                              "gsd, a flake layer's thickness_um times its flakes' volume_fraction (the texture model "
                              "follows every flake a light path crosses), and --res / --size; lower the largest, or "
                              "set FLAKEDB_MEMORY_BUDGET, e.g. FLAKEDB_MEMORY_BUDGET=4GiB)")
    if _is_loaded_instance(exc, "flakedb.bsdf.table", "BSDFFileError"):
        err = click.ClickException(_one_line(exc))
        err.exit_code = 2
        return err
    if isinstance(exc, StoreError):
        return FlakedbFailure(_one_line(exc))
    return FlakedbFailure(_one_line(f"internal error: {type(exc).__name__}: {exc} (hint: rerun with "
                                    f"`flakedb --debug ...` for the traceback and report it)"))


def missing_dirs(path) -> list[Path]:
    """The directories ``path`` and its ancestors that do not exist yet, deepest first."""
    out = []
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        out.append(p)
        p = p.parent
    return out


@contextlib.contextmanager
def remove_created_dirs(path):
    """On an exception inside the block, remove ``path`` and the ancestors the block created when
    they are empty (deepest first), then re-raise."""
    created = missing_dirs(path)
    try:
        yield
    except BaseException:
        for d in created:
            try:
                d.rmdir()  # only an empty directory goes
            except OSError:
                break
        raise


def probe_writable(out_dir, option="--out"):
    """Refuse (:class:`flakedb.cli.errors.FlakedbError`-like, exit 2) an output directory in which
    no file can be created, before any work: a temporary file is created and removed in ``out_dir``
    or its nearest existing ancestor (permissions alone do not tell: root, read-only mounts, /proc)."""
    p = Path(out_dir).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        with tempfile.TemporaryFile(dir=p):
            pass
    except OSError as e:
        err = click.ClickException(f"{option} {out_dir}: cannot create files in {p} ({e.strerror}) "
                                   f"(hint: choose a directory you can write)")
        err.exit_code = 2
        raise err from None


def check_plan(plan):
    """Check a command's :class:`flakedb.outputs.OutputPlan` before any work (an
    :class:`~flakedb.outputs.OutputError` becomes exit status 2), then remove the stale temporary
    entries killed runs left in its output directories (:func:`flakedb.outputs.sweep_stale`), each
    reported on stderr.  Returns the plan."""
    try:
        plan.check()
    except OutputError as exc:
        err = click.ClickException(_one_line(exc))
        err.exit_code = 2
        raise err from None
    dirs = {str(Path(p).parent) for p, _ in plan.outputs} | {str(d) for d, _ in plan.dirs}
    for d in sorted(dirs):
        for p in sweep_stale(d or "."):
            click.echo(f"note: removed {p}, a temporary entry left by an interrupted flakedb run", err=True)
    return plan
