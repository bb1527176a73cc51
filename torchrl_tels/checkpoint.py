"""Checkpoint files: written atomically, read with ``weights_only=True``, checked before use."""
from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path
from typing import Any

import torch

from torchrl_tels.errors import CheckpointError

__all__ = ["CheckpointError", "atomic_save", "file_sha256", "load_checkpoint"]


def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes: which checkpoint a result was made from."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def atomic_save(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save`` to a temporary file in the same folder, then rename over ``path``.

    A kill during the write leaves the previous file intact: the rename is the
    only step that touches ``path``, and it is atomic on POSIX file systems.
    """
    path = Path(path)
    folder = path.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise CheckpointError(f"cannot create the folder {folder} for {path.name}: {err}") from err
    if not os.access(folder, os.W_OK):
        raise CheckpointError(f"the folder {folder} is not writable; cannot save {path.name}.")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_folder(folder)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def _fsync_folder(folder: Path) -> None:
    """Makes the rename itself durable (a power cut right after it keeps the new file)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # platforms without directory handles
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def load_checkpoint(path: str | os.PathLike, expected_format: str) -> dict:
    """Loads a file written by :func:`atomic_save` and checks it is a ``expected_format`` file.

    ``weights_only=True`` means a file that holds arbitrary pickled objects
    is refused rather than executed.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist.")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated, corrupted, or a non-weights pickle
        raise CheckpointError(
            f"cannot read checkpoint {path}: it is truncated, corrupted, or not a "
            f"torchrl_tels checkpoint ({type(err).__name__}: {str(err).splitlines()[0][:200]})"
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != expected_format:
        found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(
            f"{path} is not a {expected_format!r} checkpoint (found format {found!r})."
        )
    return payload
