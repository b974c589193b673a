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

:class:`CheckpointWriter` runs :func:`write_checkpoint` in a background thread (the live
node's executor goes on with the frames meanwhile): one write in flight, the newest state
submitted wins, and :meth:`~CheckpointWriter.flush` waits for the last one.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import struct
import tempfile
import threading
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from stellar_cal_ros.errors import CheckpointError

__all__ = ["MAGIC", "CheckpointWriter", "read_checkpoint", "write_checkpoint"]

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


class CheckpointWriter:
    """:func:`write_checkpoint` to one path in a background thread.

    :meth:`submit` hands over a state (arrays the caller no longer changes) and returns at
    once.  One write is in flight at a time; a state submitted meanwhile waits, and a newer
    submission replaces it (the newest state wins, an older one is never written after
    it).  Each write is atomic (temporary file, fsync, rename), so a process killed during
    one leaves the previous checkpoint whole.  :meth:`flush` waits until every submitted
    state is written; :meth:`close` flushes and ends the thread (a later :meth:`submit`
    starts another).

    Parameters
    ----------
    path : str or Path
        The checkpoint file.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.written = 0  #: writes completed
        self._cond = threading.Condition()
        self._pending: tuple[dict[str, Any], dict[str, Any]] | None = None
        self._busy = False
        self._stop = False
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None

    def submit(self, arrays: dict[str, Any], meta: dict[str, Any]) -> None:
        """Write this state next (replacing a state still waiting); returns at once."""
        with self._cond:
            self._pending = (arrays, meta)
            self._stop = False
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, daemon=True,
                                                name="checkpoint-writer")
                self._thread.start()
            self._cond.notify_all()

    def take_error(self) -> BaseException | None:
        """The error of a write that failed since the last call (None: none failed)."""
        with self._cond:
            err, self._error = self._error, None
        return err

    def flush(self, timeout: float | None = None) -> None:
        """Wait until every submitted state is written; raise a failed write's error.

        Raises
        ------
        TimeoutError
            Still writing after ``timeout`` seconds.
        """
        with self._cond:
            if not self._cond.wait_for(lambda: self._pending is None and not self._busy,
                                       timeout):
                raise TimeoutError(f"{self.path}: checkpoint still being written after "
                                   f"{timeout} s")
        err = self.take_error()
        if err is not None:
            raise err

    def close(self, timeout: float | None = None) -> None:
        """:meth:`flush`, then end the thread."""
        try:
            self.flush(timeout)
        finally:
            with self._cond:
                self._stop = True
                thread = self._thread
                self._cond.notify_all()
            if thread is not None:
                thread.join(timeout)

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending is not None or self._stop)
                if self._pending is None:
                    self._thread = None  # under the lock: a later submit starts another
                    return
                (arrays, meta), self._pending = self._pending, None
                self._busy = True
            done, err = False, None
            try:
                write_checkpoint(self.path, arrays, meta)
                done = True
            except Exception as exc:  # noqa: BLE001 - kept for the owner (flush/take_error)
                err = exc
            finally:  # (whatever ends the write: flush must not wait for ever)
                with self._cond:
                    self._busy = False
                    self.written += done
                    if err is not None:
                        self._error = err
                    self._cond.notify_all()


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
