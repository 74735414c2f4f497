"""The output plan of a command (issue 25): every output path resolved and checked before any work,
written together or not at all, and the temporary entries of a killed run cleaned up.

* :class:`OutputPlan`: a command names its inputs and all its outputs first; :meth:`OutputPlan.check`
  refuses (:class:`OutputError`, exit status 2 at the command line) an output that *is* an input
  (same path, a symlink or a hard link to it), two outputs that are one file, a name that must be a
  plain file name "in --out" but is a path (``../x.png``), an output whose place is taken by a
  directory or a special file, and an output directory that cannot be created or written
  (:func:`check_output_dir`).
* :meth:`OutputPlan.staged`: the outputs are written into temporary directories beside their final
  places and moved in only when every one is complete; if a move fails, the files already moved
  are put back as they were (the previous version is kept by a hard link until the end), so the
  user finds the old set or the new set, never a mixture.
* Temporary entries are named ``.NAME.flakedb-tmp-HOST-PID-XXXX…`` (:func:`temp_prefix`, also used
  by :mod:`flakedb.atomic`), so :func:`sweep_stale` can tell ours from anything else: it removes
  only entries with that tag whose process is gone (same host) or that are older than
  :data:`STALE_AGE_S` (another host sharing the directory), and reports each one.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import socket
import stat
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

#: The tag in every temporary entry flakedb creates beside an output.
TEMP_TAG = "flakedb-tmp"
#: An entry of another host (or one whose owner cannot be told) is stale only when older than this [s].
STALE_AGE_S = 24 * 3600.0
_TEMP_RE = re.compile(rf"^\..*\.{TEMP_TAG}-(?P<host>[A-Za-z0-9-]*)-(?P<pid>\d+)-[A-Za-z0-9_]*\.tmp.*$")


class OutputError(ValueError):
    """An output cannot be written as planned (the command refuses before any work, exit status 2)."""


def temp_host() -> str:
    """This host's name as temporary entries carry it (letters, digits and '-')."""
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:32] or "host"


_host = temp_host


def temp_prefix(name: str) -> str:
    """The prefix of a temporary entry for the output ``name``: ``.NAME.flakedb-tmp-HOST-PID-``
    (``tempfile`` adds random characters, the caller ``.tmp…``)."""
    return f".{name}.{TEMP_TAG}-{_host()}-{os.getpid()}-"


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` of this host may still run (True when it cannot be told)."""
    return _pid_alive(pid)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, OSError):
        return True   # someone else's process, or cannot tell: keep the entry
    return True


def sweep_stale(directory, now=None, max_age_s=STALE_AGE_S) -> list[Path]:
    """Remove the stale temporary entries of killed flakedb runs in ``directory`` (module docstring)
    and return them.  Only entries carrying :data:`TEMP_TAG` are considered; one of a process that
    still runs on this host is never touched; a symlink is removed as a link (never followed)."""
    d = Path(directory)
    if not d.is_dir():
        return []
    now = time.time() if now is None else now
    host = _host()
    removed = []
    try:
        entries = list(os.scandir(d))
    except OSError:
        return []
    for e in entries:
        m = _TEMP_RE.match(e.name)
        if not m:
            continue
        try:
            st = e.stat(follow_symlinks=False)
        except OSError:
            continue
        pid = int(m.group("pid"))
        if m.group("host") == host:
            stale = pid != os.getpid() and not _pid_alive(pid)
        else:
            stale = now - st.st_mtime > max_age_s
        if not stale:
            continue
        p = Path(e.path)
        try:
            if stat.S_ISDIR(st.st_mode):
                shutil.rmtree(p)
            else:
                p.unlink()
        except OSError:
            continue
        removed.append(p)
    return removed


def check_output_dir(out_dir, option="--out") -> Path:
    """Refuse an output directory that cannot be created or written, before any computation.

    Creates nothing: checks that ``out_dir`` is a writable directory, or that its nearest existing
    ancestor is a writable directory (it will be created when the files are written).
    """
    p = Path(out_dir)
    if p.exists():
        if not p.is_dir():
            raise OutputError(f"{option} {out_dir}: exists and is not a directory (hint: choose a directory path)")
        if not os.access(p, os.W_OK | os.X_OK):
            raise OutputError(f"{option} {out_dir}: directory is not writable (hint: choose a directory you can write)")
        return p
    if p.is_symlink():
        raise OutputError(f"{option} {out_dir}: a broken symbolic link (hint: remove it or choose another path)")
    anc = p.absolute().parent
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise OutputError(f"{option} {out_dir}: {anc} is not a directory, so {out_dir} cannot be created")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise OutputError(f"{option} {out_dir}: cannot create it, {anc} is not writable "
                          f"(hint: choose a directory you can write)")
    return p


def check_file_name(name, option, where="--out") -> str:
    """Refuse a value that must be a plain file name in ``where`` but is a path or a special name."""
    s = str(name)
    shown = repr(s) if len(s) <= 80 else repr(s[:77]) + f"... ({len(s):,} characters)"
    if (not s or s in (".", "..") or "/" in s or (os.sep != "/" and os.sep in s) or (os.altsep and os.altsep in s)
            or "\0" in s):
        raise OutputError(f"{option} {shown}: must be a plain file name, written in {where} (no directory part, "
                          f"not '.' or '..') (hint: give e.g. {option} sheet.png and choose the directory with {where})")
    if any(ord(c) < 32 or ord(c) == 127 for c in s):
        raise OutputError(f"{option} {shown}: a file name with a control character (a line break, say) is refused "
                          f"(hint: rename it)")
    if len(os.fsencode(s)) > 255:
        raise OutputError(f"{option} {shown}: a file name is at most 255 bytes (hint: choose a shorter name)")
    return s


def _key(p: Path) -> str:
    """A comparable form of an output path: its parent resolved (symlinks followed) plus its name
    (the name itself resolved too when it is a symlink)."""
    p = Path(p)
    if p.is_symlink():
        return os.path.realpath(p)
    return os.path.join(os.path.realpath(p.parent if str(p.parent) else "."), p.name)


def _same(a: Path, b: Path) -> bool:
    if _key(a) == _key(b):
        return True
    try:
        return os.path.samefile(a, b)   # hard links, bind mounts
    except OSError:
        return False


@dataclass
class OutputPlan:
    """Inputs and outputs of one command (module docstring).

    An output that is the input is refused before any work; a valid plan's files appear only when its
    staged block ends, with no temporary entry left behind:

    >>> d = Path(tempfile.mkdtemp())
    >>> src = d / "in.bsdf"
    >>> _ = src.write_text("x")
    >>> bad = OutputPlan()
    >>> _ = bad.add_input(src, "BSDF"), bad.in_dir(d, "in.bsdf", "image")
    >>> try:
    ...     bad.check()
    ... except OutputError as e:
    ...     print(str(e).replace(str(d), "D").split(";")[0])
    image D/in.bsdf: is the input BSDF D/in.bsdf
    >>> plan = OutputPlan()
    >>> _ = plan.add_input(src, "BSDF")
    >>> out = plan.in_dir(d, "out.png", "image")
    >>> with plan.check().staged() as stage:
    ...     _ = stage.path(out).write_text("new")
    ...     print(out.exists())
    False
    >>> out.read_text(), sorted(p.name for p in d.iterdir())
    ('new', ['in.bsdf', 'out.png'])
    """

    inputs: list = field(default_factory=list)    # (Path, label)
    outputs: list = field(default_factory=list)   # (Path, label)
    dirs: list = field(default_factory=list)      # (Path, option)
    errors: list = field(default_factory=list)    # OutputError found while planning

    def add_input(self, path, label):
        if path is not None:
            self.inputs.append((Path(path), label))
        return path

    def add_output(self, path, label) -> Path:
        p = Path(path)
        self.outputs.append((p, label))
        return p

    def add_dir(self, out_dir, option="--out") -> Path:
        self.dirs.append((Path(out_dir), option))
        return Path(out_dir)

    def in_dir(self, out_dir, name, label, option=None, where="--out") -> Path:
        """``out_dir / name`` as an output; ``option`` given: ``name`` came from that option and must be a
        plain file name (:func:`check_file_name`)."""
        if option is not None:
            try:
                check_file_name(name, option, where)
            except OutputError as exc:   # reported by check(), with the rest of the plan
                self.errors.append(exc)
        return self.add_output(Path(out_dir) / name, label)

    def check(self):
        """Refuse the plan (:class:`OutputError`) for the reasons in the module docstring."""
        if self.errors:
            raise self.errors[0]
        for d, option in self.dirs:
            check_output_dir(d, option)
        seen = []
        for p, label in self.outputs:
            check_output_dir(p.parent if str(p.parent) else Path("."), f"{label} {p}: its directory")
            if p.is_symlink() and not p.exists():
                raise OutputError(f"{label} {p}: a broken symbolic link is in its place (hint: remove it)")
            if p.exists():
                st = os.stat(p)
                if stat.S_ISDIR(st.st_mode):
                    raise OutputError(f"{label} {p}: a directory is in its place; nothing was written "
                                      f"(hint: remove or rename the directory, or choose another --out)")
                if not stat.S_ISREG(st.st_mode):
                    raise OutputError(f"{label} {p}: a special file (not a regular file) is in its place; "
                                      f"nothing was written (hint: choose another name)")
            for q, qlabel in self.inputs:
                if _same(p, q):
                    raise OutputError(f"{label} {p}: is the input {qlabel} {q}; writing it would destroy the "
                                      f"input, so nothing was written (hint: choose another output name or "
                                      f"directory)")
            for q, qlabel in seen:
                if _same(p, q):
                    raise OutputError(f"{label} {p} and {qlabel} {q} are the same file: one would overwrite "
                                      f"the other, so nothing was written (hint: rename one of the inputs or "
                                      f"choose distinct names)")
            seen.append((p, label))
        return self

    @contextlib.contextmanager
    def staged(self):
        """Context manager yielding a :class:`Stage`: write each output to ``stage.path(final)``; when the
        block ends normally every staged file is moved to its final place together (module docstring),
        on any error (a signal included) nothing is moved and the staging directories are removed."""
        stage = Stage()
        try:
            yield stage
            stage.commit([p for p, _ in self.outputs])
        finally:
            stage.cleanup()


class Stage:
    """Temporary directories beside the outputs (one per directory), see :meth:`OutputPlan.staged`."""

    def __init__(self):
        self.dirs = {}

    def dir_for(self, directory) -> Path:
        key = os.path.realpath(directory)
        if key not in self.dirs:
            Path(directory).mkdir(parents=True, exist_ok=True)
            self.dirs[key] = Path(tempfile.mkdtemp(dir=directory, prefix=temp_prefix("out"), suffix=".tmp"))
        return self.dirs[key]

    def path(self, final) -> Path:
        final = Path(final)
        return self.dir_for(final.parent if str(final.parent) else ".") / final.name

    def commit(self, finals):
        """Move every staged file of ``finals`` into place; a failure puts back what was moved."""
        mask = os.umask(0)
        os.umask(mask)
        todo = []
        for f in finals:
            s = self.path(f)
            if s.exists():
                os.chmod(s, 0o666 & ~mask)   # temp files are 0600: give them the usual umask mode
                todo.append((Path(f), s))
        backups = {}
        for f, s in todo:   # keep each previous version reachable until every move is done
            if f.exists():
                b = s.with_name(s.name + ".previous")
                try:
                    os.link(f, b)
                    backups[f] = b
                except OSError:
                    pass
        moved = []
        try:
            for f, s in todo:
                os.replace(s, f)
                moved.append(f)
        except BaseException:
            for f in moved:
                with contextlib.suppress(OSError):
                    if f in backups:
                        os.replace(backups[f], f)
                    else:
                        f.unlink()
            raise

    def cleanup(self):
        for d in self.dirs.values():
            shutil.rmtree(d, ignore_errors=True)
        self.dirs = {}
