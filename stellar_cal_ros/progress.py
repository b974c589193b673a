"""Progress bars with ETA (tqdm); plain, complete lines when stderr is not a terminal."""

from __future__ import annotations

import sys
import time


class _Lines:
    """A progress report in plain lines (every 10 %), for logs and pipes."""

    def __init__(self, total: float, desc: str, unit: str) -> None:
        self.total, self.desc, self.unit = float(total), desc, unit
        self.n = 0.0
        self.next = 0.1
        self.t0 = time.perf_counter()

    def update(self, n: float = 1) -> None:
        self.n += n
        frac = self.n / self.total if self.total else 1.0
        if frac >= self.next:
            el = time.perf_counter() - self.t0
            eta = el * (1 - frac) / max(frac, 1e-9)
            print(f"{self.desc}: {100 * min(frac, 1):.0f} % ({el:.1f} s, ETA {eta:.0f} s)",
                  file=sys.stderr, flush=True)
            while self.next <= frac:
                self.next += 0.1

    def close(self) -> None:
        pass


def progress(total: float, desc: str = "", unit: str = "it"):
    """A progress bar with ``update(n)`` and ``close()``."""
    if sys.stderr.isatty():
        from tqdm import tqdm

        return tqdm(total=total, desc=desc, unit=unit, leave=False,
                    bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}")
    return _Lines(total, desc, unit)
