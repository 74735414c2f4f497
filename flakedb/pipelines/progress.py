"""Progress of a build on stderr, suited to where stderr goes (issue 13).

On a terminal: one live bar redrawn in place (at most 10 times a second).  Into a log (stderr not a
TTY): a few summary lines (start, every 25 %, end) instead of hundreds of carriage-return frames.
Never on stdout (which carries the command's result).
"""

from __future__ import annotations

import sys
import time


class BuildProgress:
    """Count finished tasks and report them; ``update(k)`` after ``k`` more tasks, ``close()`` at the end.

    Into a log (not a terminal) a build of 8 tasks writes its start, each quarter and its end:

    >>> import io
    >>> log = io.StringIO()
    >>> p = BuildProgress(8, stream=log, tty=False)
    >>> for _ in range(8):
    ...     p.update()
    >>> p.close()
    >>> print(log.getvalue())
    build: 8 task(s) to run
    build: 2/8 tasks done (25%), ... s
    build: 4/8 tasks done (50%), ... s
    build: 6/8 tasks done (75%), ... s
    build: 8/8 tasks done in ... s
    <BLANKLINE>
    """

    def __init__(self, total: int, label: str = "build", stream=None, tty: bool | None = None, width: int = 30):
        self.total, self.label, self.width = int(total), label, width
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)()) if tty is None else tty
        self.done = 0
        self.t0 = time.perf_counter()
        self._last_draw = 0.0
        self._next_quarter = 1
        self._closed = False
        if not self.tty:
            self._line(f"{self.label}: {self.total} task(s) to run")
        else:
            self._draw(force=True)

    def _line(self, text):
        self.stream.write(text + "\n")
        self.stream.flush()

    def _draw(self, force=False):
        now = time.perf_counter()
        if not force and now - self._last_draw < 0.1:
            return
        self._last_draw = now
        frac = self.done / self.total if self.total else 1.0
        fill = int(round(frac * self.width))
        self.stream.write(f"\r{self.label}: [{'#' * fill}{' ' * (self.width - fill)}] {self.done}/{self.total} "
                          f"tasks {100 * frac:3.0f}% {now - self.t0:6.1f} s")
        self.stream.flush()

    def update(self, k: int = 1):
        self.done = min(self.total, self.done + int(k))
        if self.tty:
            self._draw(force=self.done == self.total)
            return
        quarter = self.done * 4 // self.total if self.total else 4
        if self._next_quarter <= quarter < 4:  # one line per quarter reached (the end has its own)
            self._line(f"{self.label}: {self.done}/{self.total} tasks done ({100 * self.done // self.total}%), "
                       f"{time.perf_counter() - self.t0:.1f} s")
            self._next_quarter = quarter + 1

    def close(self):
        if self._closed:
            return
        self._closed = True
        took = time.perf_counter() - self.t0
        if self.tty:
            self._draw(force=True)
            self.stream.write("\n")
            self.stream.flush()
        else:
            self._line(f"{self.label}: {self.done}/{self.total} tasks done in {took:.1f} s")
