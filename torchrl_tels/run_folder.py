"""One run, one folder: a run claims its ``run_dir`` so no other run can write into it.

A fresh run refuses a folder that already holds files (another run's, finished or not) unless
the user asks to overwrite it, and two runs started at once on one folder cannot both claim it:
the claim is an exclusive ``flock`` on a lock file inside the folder, held until the process
exits. ``resume=true`` takes the same claim, so a folder is continued by one process at a time.
"""
from __future__ import annotations

import fcntl
import os
import shutil
from pathlib import Path

from torchrl_tels.errors import ConfigError

__all__ = ["LOCK_NAME", "RunFolderClaim", "check_run_dir_free", "claim_run_dir"]

#: the lock file a run holds in its folder; it marks nothing by itself and is never counted as a run's file
LOCK_NAME = ".tels-run.lock"


def _run_files(folder: Path) -> list[str]:
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir() if p.name != LOCK_NAME)


def _refusal(folder: Path, files: list[str]) -> ConfigError:
    shown = ", ".join(files[:4]) + (f" and {len(files) - 4} more" if len(files) > 4 else "")
    return ConfigError(
        f"run_dir {folder} already holds another run's files ({shown}); continue that run with resume=true, "
        f"choose a new run_dir, or pass overwrite=true to write over it.")


def check_run_dir_free(folder: str | os.PathLike, *, resume: bool, overwrite: bool) -> None:
    """Refuses, before anything is loaded or written, a fresh run into a folder that holds files.

    This early check gives the clear error; :func:`claim_run_dir` makes the claim race-free.
    """
    folder = Path(folder)
    if not (resume or overwrite) and (files := _run_files(folder)):
        raise _refusal(folder, files)


class RunFolderClaim:
    """An exclusive claim on a run folder; released by :meth:`release` or when the process exits."""

    def __init__(self, folder: Path, fd: int) -> None:
        self.folder, self._fd = folder, fd

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "RunFolderClaim":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def claim_run_dir(folder: str | os.PathLike, *, resume: bool, overwrite: bool) -> RunFolderClaim:
    """Creates ``folder`` and claims it for this process.

    Raises :class:`ConfigError` when another live process holds the folder, or when a fresh run
    (``resume=false``) finds files there and ``overwrite`` is false. With ``overwrite=true`` the old
    run's files are deleted (all of them: its logs, checkpoints and ``seed<k>/`` folders would otherwise
    mix with the new run's), and only from a folder that holds a run (a ``config.yaml``): ``overwrite``
    never deletes a folder of other files. Checked under the lock, so of two runs started at once
    exactly one proceeds.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder / LOCK_NAME, os.O_CREAT | os.O_RDWR, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise ConfigError(f"run_dir {folder} is in use by another running job; choose a new run_dir, or wait for "
                          f"it to end and continue it with resume=true.") from None
    except OSError as err:  # a file system without locks (some NFS or Lustre mounts)
        os.close(fd)
        raise ConfigError(f"run_dir {folder} cannot be locked ({err.strerror or err}): its file system does not "
                          "support flock; choose a run_dir on a local or lock-capable file system.") from None
    claim = RunFolderClaim(folder, fd)
    if not resume:
        files = _run_files(folder)
        if files and not overwrite:
            claim.release()
            raise _refusal(folder, files)
        if files and not (folder / "config.yaml").is_file():
            claim.release()
            raise ConfigError(f"run_dir {folder} holds files but no run (no config.yaml): overwrite=true deletes only "
                              "a run's folder; choose a new run_dir.")
        for name in files:
            path = folder / name
            shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return claim
