"""Progress of a long command on stderr: one line that updates in place on a terminal, plain lines
otherwise (a log file, a pipe, CI).  Warnings always get their own line."""

import sys
import time

import click


class StageProgress:
    """``progress(stage, detail)`` callback of :func:`flakedb.compose.orchestrate.compose` (and the
    solver's :class:`flakedb.rt.adding.stack.SolverSettings` ``progress``): stages optics, discretisation, projection, solve,
    channels, write and warning.  ``stream`` defaults to stderr; ``tty`` to whether it is a terminal.

    Into a log, one time-stamped line per event:

    >>> import io
    >>> log = io.StringIO()
    >>> progress = StageProgress(log, tty=False)
    >>> progress("optics", {"start": True})
    >>> progress("optics", {"channels": 3, "seconds": 1.5})
    >>> print(log.getvalue())
    [... s] optics: particle optics…
    [... s] optics: done (3 channel(s), 1.5 s)
    <BLANKLINE>
    """

    def __init__(self, stream=None, tty=None):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty() if tty is None else bool(tty)
        self.t0 = time.perf_counter()
        self.open_line = False

    def _emit(self, text, final=False):
        stamp = f"[{time.perf_counter() - self.t0:6.1f} s] "
        if self.tty and not final:
            click.echo("\r\033[K" + stamp + text, file=self.stream, nl=False)
            self.open_line = True
            self.stream.flush()
        else:
            if self.open_line:
                click.echo("\r\033[K", file=self.stream, nl=False)
                self.open_line = False
            click.echo(stamp + text, file=self.stream)

    def __call__(self, stage, detail):
        d = detail or {}
        if stage == "warning":
            self._emit(f"warning: {d.get('message')}", final=True)
        elif stage == "optics":
            self._emit("optics: particle optics…" if d.get("start") else
                       f"optics: done ({d.get('channels')} channel(s), {d.get('seconds', 0):.1f} s)")
        elif stage == "projection":
            self._emit(f"projection: layer {d['layer']}/{d['layers']} kernel projected ({d.get('orders')} orders)")
        elif stage == "solve":
            l0, l1 = d.get("orders", (0, 0))
            self._emit(f"solve: layer {d['layer']}/{d['layers']}, Fourier orders {l0}-{l1 - 1} "
                       f"(at most {d.get('of')})")
        elif stage == "channels":
            c0, c1 = d["channels"]
            self._emit(f"solve: spectral channels {c0 + 1}-{c1} of {d['of']}")
        elif stage == "discretisation":
            self._emit(f"discretisation: second solve at n = {d.get('n')} (the report's error estimate)…"
                       if d.get("start") else f"discretisation: second solve done ({d.get('seconds', 0):.1f} s)")
        elif stage == "write":
            self._emit("write: .bsdf, .h5, .json…" if d.get("start") else
                       f"write: done ({d.get('seconds', 0):.1f} s)", final=not d.get("start"))
        else:
            self._emit(f"{stage}: {d}")

    def close(self):
        if self.open_line:
            click.echo("", file=self.stream)
            self.open_line = False
