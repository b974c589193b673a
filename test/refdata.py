"""The independent reference data beside the repository: ``../shared/data`` (bags, priors,
truths from another generator) and ``../shared/realsky`` (real night-sky frames).

One place says where they are; a clone has no ``../shared``, so every test that needs them
skips with the reason shown (``-rs``): :func:`needs` marks a test, :func:`path` skips from
inside one, :func:`files` lists what is there (empty when absent); the ``reference_data``
fixture (``conftest.py``) is the folder itself.
"""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"
DATA = SHARED / "data"
REALSKY = SHARED / "realsky"


def _reason(missing: Path) -> str:
    return f"reference data not found: {missing} (a clone has no ../shared)"


def needs(*names: str, folder: Path = DATA) -> pytest.MarkDecorator:
    """Skip the test unless every file (or the folder, without names) exists."""
    targets = [folder / n for n in names] or [folder]
    missing = next((p for p in targets if not p.exists()), None)
    return pytest.mark.skipif(missing is not None, reason=_reason(missing or folder))


def path(name: str, folder: Path = DATA) -> Path:
    """The file ``name`` of the reference folder; skips the calling test when it is absent."""
    p = folder / name
    if not p.exists():
        pytest.skip(_reason(p))
    return p


def files(pattern: str, folder: Path = DATA) -> list[Path]:
    """The folder's files matching ``pattern``, sorted (empty when the folder is absent)."""
    return sorted(folder.glob(pattern)) if folder.is_dir() else []
