"""One run, one folder: :class:`RunFolder` owns the layout of a recipe run's ``run_dir``, for the run that
writes it and for whatever reads it afterwards (export, summaries, the study).

A run claims its folder so no other run can write into it. A fresh run refuses a folder that already holds files (another run's, finished or not) unless
the user asks to overwrite it, and two runs started at once on one folder cannot both claim it:
the claim is an exclusive ``flock`` on a lock file inside the folder, held until the process
exits. ``resume=true`` takes the same claim, so a folder is continued by one process at a time.
"""
from __future__ import annotations

import fcntl
import json
import os
import shutil
from pathlib import Path
from typing import Any, Mapping

from torchrl_tels.errors import CheckpointError, ConfigError

__all__ = ["LOCK_NAME", "RunFolder", "RunFolderClaim", "check_run_dir_free", "claim_run_dir"]

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


def _file_in_folder(name: str) -> property:
    """The path of the run folder's file ``name``, as a read-only attribute."""
    return property(lambda folder: folder.path / name, doc=f"``run_dir/{name}``")


class RunFolder:
    """A recipe run's folder: where each of its files lives, how it is claimed, and what it holds.

    The run writes ``config.yaml`` (the resolved config), ``state.pt`` (what ``resume=true`` continues from),
    ``tsidm.pt`` (and ``best_tsidm.pt`` while β candidates train), ``policy.pt``, ``monitor.pt`` and, once it
    has finished, ``results.json``. A run of several seeds keeps each seed's own run folder in ``seed<k>/``
    and writes an aggregate ``results.json`` of its own. Readers open a folder with :meth:`open_finished`
    (or walk many with :meth:`find`) and read through it, so the layout is written down here only.
    """

    CONFIG, RESULTS, STATE = "config.yaml", "results.json", "state.pt"
    TSIDM, BEST_TSIDM, POLICY, MONITOR = "tsidm.pt", "best_tsidm.pt", "policy.pt", "monitor.pt"
    EXPORT = "export"

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)

    def __fspath__(self) -> str:
        # a path-like: the functions that take a run_dir take a RunFolder too
        return os.fspath(self.path)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, RunFolder) and other.path == self.path

    def __hash__(self) -> int:
        return hash(self.path)

    # ------------------------------------------------------------------ layout
    config_path = _file_in_folder(CONFIG)
    results_path = _file_in_folder(RESULTS)
    state_path = _file_in_folder(STATE)
    tsidm_path = _file_in_folder(TSIDM)
    best_tsidm_path = _file_in_folder(BEST_TSIDM)
    policy_path = _file_in_folder(POLICY)
    monitor_path = _file_in_folder(MONITOR)
    export_path = _file_in_folder(EXPORT)

    def seed(self, seed: int) -> "RunFolder":
        """The run folder of ``seed`` inside a run of several seeds."""
        return RunFolder(self.path / f"seed{seed}")

    def seed_folders(self) -> list["RunFolder"]:
        """The per-seed run folders (``seed<k>/`` holding a config) of a run of several seeds; empty for one seed."""
        if not self.path.is_dir():
            return []
        return [RunFolder(p) for p in sorted(self.path.iterdir())
                if p.name.startswith("seed") and p.is_dir() and (p / self.CONFIG).exists()]

    # ------------------------------------------------------------------ writing
    def check_free(self, *, resume: bool, overwrite: bool) -> None:
        """:func:`check_run_dir_free` on this folder."""
        check_run_dir_free(self.path, resume=resume, overwrite=overwrite)

    def claim(self, *, resume: bool, overwrite: bool) -> RunFolderClaim:
        """:func:`claim_run_dir` on this folder."""
        return claim_run_dir(self.path, resume=resume, overwrite=overwrite)

    def write_config(self, text: str) -> None:
        """The resolved config as YAML ``text``, written atomically (the folder is created if need be)."""
        from torchrl_tels.training import write_text

        self.path.mkdir(parents=True, exist_ok=True)
        write_text(self.config_path, text)

    def write_results(self, results: Mapping[str, Any]) -> None:
        """``results.json``, written atomically: its presence marks the run finished."""
        from torchrl_tels.training import write_json

        write_json(self.results_path, results)

    # ------------------------------------------------------------------ reading
    @property
    def is_finished(self) -> bool:
        return self.results_path.is_file()

    def missing(self, names) -> list[str]:
        """Those of the files ``names`` (of this layout's, e.g. :attr:`POLICY`) that the folder lacks."""
        return [name for name in names if not (self.path / name).exists()]

    def status(self) -> str:
        """``"finished"`` (it has ``results.json``), ``"running"`` (a live process holds its lock) or
        ``"unfinished"`` (stopped or failed)."""
        if self.is_finished:
            return "finished"
        lock = self.path / LOCK_NAME
        if lock.is_file():
            fd = os.open(lock, os.O_RDONLY)
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return "running"
            finally:
                os.close(fd)
        return "unfinished"

    def read_results(self) -> dict:
        """The run's ``results.json``; :class:`CheckpointError` when it is missing or unreadable."""
        try:
            payload = json.loads(self.results_path.read_text())
        except FileNotFoundError:
            raise CheckpointError(f"{self.path} has no results.json: the run has not finished (or it is not a run "
                                  "folder).") from None
        except (OSError, ValueError) as err:
            raise CheckpointError(f"cannot read {self.results_path}: {err}") from None
        if not isinstance(payload, dict):
            raise CheckpointError(f"{self.results_path} does not hold a run's results.")
        return payload

    def read_config(self) -> dict:
        """The run's ``config.yaml`` as plain containers (``{}`` for an empty file)."""
        import yaml

        try:
            return yaml.safe_load(self.config_path.read_text()) or {}
        except FileNotFoundError:
            raise CheckpointError(f"{self.path} has no config.yaml: it is not a run folder.") from None

    @classmethod
    def open_finished(cls, path: str | os.PathLike, required: tuple[str, ...] = (), *,
                      purpose: str = "read it") -> "RunFolder":
        """The folder of a finished run at ``path``, holding the files named in ``required`` besides
        ``results.json``; :class:`CheckpointError` naming what is missing otherwise, and that the run can be
        finished first and then used for ``purpose``."""
        folder = cls(path)
        if not folder.path.is_dir():
            raise CheckpointError(f"{folder.path} is not a folder; pass the run folder of a finished run.")
        if not folder.is_finished:
            raise CheckpointError(f"{folder.path} has no results.json: the run has not finished (or it is not a "
                                  f"run folder); finish it with resume=true, then {purpose}.")
        if missing := folder.missing(required):
            raise CheckpointError(f"{folder.path} is a finished run without {', '.join(missing)}.")
        return folder

    @classmethod
    def find(cls, top: str | os.PathLike) -> list["RunFolder"]:
        """Every run folder (one holding ``config.yaml``) under ``top``, itself included, in path order. A run of
        several seeds counts as its seeds' folders, not as the folder that aggregates them."""
        folders = [cls(config.parent) for config in sorted(Path(top).rglob(cls.CONFIG))]
        return [folder for folder in folders if not folder.seed_folders()]
