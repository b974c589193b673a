"""Progress reporting for long commands: a bar with ETA on a terminal, plain lines elsewhere.

One helper for every long loop (replay frames, diagnosis candidates, batch stages)::

    from stellar_cal_ros.progress import progress

    with progress(len(frames), "replay", unit="frames") as p:
        for frame in frames:
            ...
            p.update(1)

    with progress(len(candidates), "diagnose", unit="candidates") as p:
        for k, effect in enumerate(candidates):
            p.note(f"candidate {k + 1}/{len(candidates)}: {effect}")   # + ", ETA 40 s"
            ...
            p.update(1)

On a terminal (``stream.isatty()``) it draws a tqdm bar; log records emitted meanwhile are
routed through ``tqdm.write`` so that they do not glue onto the bar.  Anywhere else (a
pipe, a CI log, a file) it prints nothing but complete lines: one each time another
``step`` (default 10 %) of the total is done, and one at the end, e.g.
``replay: 40% (360/900 frames), 12.1 s elapsed, ETA 18.2 s``.  ``enabled=False`` prints
nothing at all (``--quiet``); notes are still printed then only if ``notes=True``.

The environment variable ``STELLAR_CAL_PROGRESS`` overrides the choice: ``bar``, ``lines``
or ``off``.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import time
from typing import TextIO

__all__ = ["COMPILE_NOTICE", "Progress", "compile_notice_armed", "first_compile",
           "format_seconds", "progress"]

#: the line a command prints before its first run here compiles the numba kernels
COMPILE_NOTICE = ("first run here: compiling the filter's numba kernels (about a minute, "
                  "once; cached for later runs and checkouts: python -m "
                  "stellar_cal_ros.diagnosis.warm_up compiles them ahead)")
#: where :func:`first_compile` says :data:`COMPILE_NOTICE` (None: nowhere, or said)
_COMPILE_STREAM: list[TextIO | None] = [None]


def compile_notice_armed(stream: TextIO | None) -> None:
    """Say :data:`COMPILE_NOTICE` on ``stream`` at this process's first kernel compile.

    The command line arms it for every command (None disarms: the notice was said ahead).
    The check ahead (:func:`~stellar_cal_ros.methods.frame_step.compile_notice`) judges
    the kernels a run here used; a kernel no run has used yet (another command's, another
    method's) compiles at its first call: said then, once.
    """
    _COMPILE_STREAM[0] = stream


def first_compile() -> None:
    """A package kernel is compiled (not in the cache): say so once when armed."""
    stream, _COMPILE_STREAM[0] = _COMPILE_STREAM[0], None
    if stream is not None:
        print(COMPILE_NOTICE, file=stream, flush=True)


def format_seconds(s: float) -> str:
    """``42 s``, ``3 min 05 s``, ``1 h 02 min``; ``?`` when unknown."""
    if not math.isfinite(s) or s < 0:
        return "?"
    if s < 60:
        return f"{s:.0f} s" if s >= 9.5 else f"{s:.1f} s"
    if s < 3600:
        return f"{int(s // 60)} min {int(s % 60):02d} s"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"


class Progress:
    """Progress of one loop of ``total`` items (see the module docstring).

    Parameters
    ----------
    total : int
        Number of items (frames, candidates, stages); 0 or less: unknown, no ETA.
    desc : str
        Short name printed first (the command: ``replay``, ``diagnose``, ``acf``).
    unit : str
        Name of the items, e.g. ``frames``.
    stream : text stream, optional
        Where to write (default ``sys.stderr``).
    enabled : bool
        False: print nothing (the bar and the 10 % lines), except notes when ``notes``.
    step : float
        Fraction of the total between two plain lines (non-terminal mode).
    mode : {'auto', 'bar', 'lines', 'off'}
        ``auto``: a bar on a terminal, lines otherwise (or ``STELLAR_CAL_PROGRESS``).
    notes : bool
        Print :meth:`note` lines even when ``enabled`` is False.
    """

    def __init__(self, total: int, desc: str, unit: str = "", stream: TextIO | None = None,
                 enabled: bool = True, step: float = 0.1, mode: str = "auto",
                 notes: bool = False) -> None:
        self.total = int(total) if total and total > 0 else 0
        self.desc = desc
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.step = step if step > 0 else 0.1
        self.n = 0
        self.start = time.perf_counter()
        self._next_line = self.step
        self._closed = False
        self._notes = notes or enabled
        mode = os.environ.get("STELLAR_CAL_PROGRESS", mode) if mode == "auto" else mode
        if mode not in ("auto", "bar", "lines", "off"):
            mode = "auto"
        if not enabled:
            mode = "off"
        elif mode == "auto":
            isatty = getattr(self.stream, "isatty", None)
            mode = "bar" if callable(isatty) and isatty() else "lines"
        self.mode = mode
        self._bar = None
        self._redirect = contextlib.ExitStack()
        if mode == "bar":
            from tqdm import tqdm
            from tqdm.contrib.logging import logging_redirect_tqdm

            self._bar = tqdm(total=self.total or None, desc=desc, unit=f" {unit}" if unit
                             else "it", file=self.stream, dynamic_ncols=True, leave=True)
            self._redirect.enter_context(logging_redirect_tqdm())

    # ------------------------------------------------------------------ timing
    @property
    def elapsed(self) -> float:
        """Seconds since the start."""
        return time.perf_counter() - self.start

    def eta(self) -> float:
        """Seconds left at the mean rate so far (NaN when unknown)."""
        if not self.total or self.n <= 0:
            return float("nan")
        return self.elapsed / self.n * max(self.total - self.n, 0)

    # ------------------------------------------------------------------ output
    def _line(self, text: str) -> None:
        self.stream.write(text + "\n")
        self.stream.flush()

    def update(self, n: int = 1) -> None:
        """``n`` more items are done."""
        self.n += n
        if self.mode == "bar":
            self._bar.update(n)
        elif self.mode == "lines" and self.total:
            frac = self.n / self.total
            if frac + 1e-12 >= self._next_line and self.n < self.total:
                while self._next_line <= frac + 1e-12:
                    self._next_line += self.step
                self._line(f"{self.desc}: {100 * frac:.0f}% ({self.n:.0f}/{self.total:.0f}"
                           f"{' ' + self.unit if self.unit else ''}), "
                           f"{format_seconds(self.elapsed)} elapsed, "
                           f"ETA {format_seconds(self.eta())}")

    def note(self, text: str, eta: bool = True) -> None:
        """One complete line about the item being worked on (``, ETA 40 s`` appended)."""
        if not self._notes:
            return
        left = self.eta()
        if eta and math.isfinite(left):
            text = f"{text}, ETA {format_seconds(left)}"
        if self.mode == "bar":
            self._bar.write(text, file=self.stream)
        else:
            self._line(text)

    def close(self, failed: bool = False) -> None:
        """End: close the bar, or print the final plain line (not when ``failed``).

        ``failed``: the work stopped on an error (the ``with`` block raised), which the
        command says in its own one line: no "done (0/5 stages)" before it (H284).
        """
        if self._closed:
            return
        self._closed = True
        if self.mode == "bar":
            self._bar.close()
        elif self.mode == "lines" and not failed:
            count = f"{self.n}/{self.total}" if self.total else f"{self.n}"
            self._line(f"{self.desc}: done ({count}{' ' + self.unit if self.unit else ''}) "
                       f"in {format_seconds(self.elapsed)}")
        self._redirect.close()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close(failed=exc_type is not None)


def progress(total: int, desc: str = "", unit: str = "", stream: TextIO | None = None,
             enabled: bool = True, step: float = 0.1, mode: str = "auto",
             notes: bool = False) -> Progress:
    """A :class:`Progress` (same parameters).

    Use it as a context manager (``with progress(n, "replay") as p: ...``, closed on exit)
    or hold it (``p = progress(n, "replay"); p.update(1); ...; p.close()``).
    """
    return Progress(total, desc, unit=unit, stream=stream, enabled=enabled, step=step,
                    mode=mode, notes=notes)
