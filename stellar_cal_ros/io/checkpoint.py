"""Checkpoint files: named arrays + JSON metadata, written atomically, verified on reading.

Layout (one file)::

    MAGIC (16 bytes)  payload length (uint64 LE)  SHA-256 of the payload (32 bytes)  payload

The payload is an uncompressed ``.npz`` (numpy's zip of ``.npy`` arrays) holding the arrays
and the metadata as UTF-8 JSON in the array ``__meta__``; arrays are loaded with
``allow_pickle=False``.  :func:`write_checkpoint` writes a temporary file in the target's
directory, flushes and fsyncs it, renames it over the target (atomic on POSIX) and fsyncs
the directory, so a crash at any moment leaves either the old or the new checkpoint, never
a mixture.  :func:`read_checkpoint` checks the magic, the length (a truncated file) and the
checksum (corrupt bytes) before decoding, and raises :class:`~stellar_cal_ros.errors.
CheckpointError` with one line naming what is wrong.

Files written before the checksum existed (a bare ``.npz`` with the metadata in ``meta``) are
still read, without verification.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import struct
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from stellar_cal_ros.errors import CheckpointError

__all__ = ["MAGIC", "read_checkpoint", "write_checkpoint"]

log = logging.getLogger(__name__)

MAGIC = b"STELLARCAL_CKPT1"
_HEAD = struct.Struct("<16sQ32s")
_META = "__meta__"


def write_checkpoint(path: str | os.PathLike[str], arrays: dict[str, Any],
                     meta: dict[str, Any]) -> Path:
    """Write ``arrays`` and ``meta`` to ``path`` atomically, with a checksum.

    Parameters
    ----------
    path : str or Path
        Target file (its directory is created if needed).
    arrays : dict of str to array_like
        Named arrays (numeric or bool; object arrays are refused).
    meta : dict
        JSON-serializable metadata.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    CheckpointError
        An array name is reserved or an array holds Python objects.
    OSError
        The file cannot be written (disk full, permissions); the old file is kept.
    """
    if _META in arrays:
        raise CheckpointError(f"array name {_META!r} is reserved")
    arrs = {k: np.asarray(v) for k, v in arrays.items()}
    bad = [k for k, a in arrs.items() if a.dtype.hasobject]
    if bad:
        raise CheckpointError(f"checkpoint arrays must not hold Python objects: {bad}")
    arrs[_META] = np.frombuffer(json.dumps(meta, allow_nan=True).encode(), dtype=np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrs)
    payload = buf.getvalue()
    head = _HEAD.pack(MAGIC, len(payload), hashlib.sha256(payload).digest())
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(head)
            fh.write(payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    return path


def _fsync_dir(directory: Path) -> None:
    """Make a rename durable (best effort: not every platform can open a directory)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def read_checkpoint(path: str | os.PathLike[str]) -> tuple[dict[str, np.ndarray],
                                                           dict[str, Any]]:
    """Read and verify a file written by :func:`write_checkpoint`.

    Returns
    -------
    arrays : dict of str to ndarray
    meta : dict

    Raises
    ------
    CheckpointError
        Missing, truncated, checksum mismatch, not a checkpoint, or undecodable.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise CheckpointError(f"{path}: checkpoint not found") from None
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read the checkpoint: {exc}") from None
    if not data:
        raise CheckpointError(f"{path}: empty checkpoint file")
    if data[:len(MAGIC)] == MAGIC or MAGIC.startswith(data):
        if len(data) < _HEAD.size:
            raise CheckpointError(f"{path}: truncated checkpoint ({len(data)} bytes, header "
                                  "incomplete)")
        _, n, digest = _HEAD.unpack_from(data)
        payload = data[_HEAD.size:]
        if len(payload) != n:
            what = "truncated" if len(payload) < n else "overlong"
            raise CheckpointError(f"{path}: {what} checkpoint ({len(payload)} of {n} payload "
                                  "bytes)")
        if hashlib.sha256(payload).digest() != digest:
            raise CheckpointError(f"{path}: checkpoint checksum mismatch (corrupt data)")
        return _decode(path, payload, _META)
    if data[:4] == b"PK\x03\x04":  # a bare .npz of the first checkpoint format
        log.warning("%s: checkpoint without a checksum (older format); not verified", path)
        return _decode(path, data, "meta")
    raise CheckpointError(f"{path}: not a checkpoint file (unknown header)")


def _decode(path: Path, payload: bytes, meta_key: str) -> tuple[dict[str, np.ndarray],
                                                                  dict[str, Any]]:
    try:
        with np.load(io.BytesIO(payload), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(bytes(arrays.pop(meta_key)).decode())
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile,
            UnicodeDecodeError) as exc:
        raise CheckpointError(f"{path}: unreadable checkpoint ({type(exc).__name__}: {exc})"
                              ) from None
    if not isinstance(meta, dict):
        raise CheckpointError(f"{path}: checkpoint metadata is not a mapping")
    return arrays, meta
