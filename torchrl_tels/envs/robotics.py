"""Gymnasium-Robotics, imported on demand: one install hint, and maze builds that leave no files behind.

The maze (AntMaze, PointMaze) and Adroit environments come from Gymnasium-Robotics, an optional
dependency (the ``robotics`` extra). Each maze env Gymnasium-Robotics builds writes its MuJoCo model
to ``<system temp>/ant_maze<time>.xml`` and never removes it; :func:`maze_files_removed` builds inside a
private folder and deletes it once the model is loaded.
"""
from __future__ import annotations

import contextlib
import io
import shutil
import tempfile
from collections.abc import Iterator

from torchrl_tels.errors import MissingDependencyError

__all__ = ["INSTALL_HINT", "import_gymnasium_robotics", "maze_files_removed"]

#: how to install the optional dependency, named in every error about it
INSTALL_HINT = 'pip install "torchrl-tels[robotics]"  (or: pip install "gymnasium-robotics>=1.4.2,<1.5")'


def import_gymnasium_robotics():
    """Import and return :mod:`gymnasium_robotics`, or say in one line how to install it.

    The package prints a notice about its Adroit environments on import; it is silenced here.

    Raises:
        MissingDependencyError: (an ``ImportError``) Gymnasium-Robotics is not installed; the message
            names the extra to install.
    """
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            import gymnasium_robotics
    except ImportError as err:
        raise MissingDependencyError(
            f"The maze and Adroit environments need Gymnasium-Robotics, which is not installed: {INSTALL_HINT}"
        ) from err
    return gymnasium_robotics


@contextlib.contextmanager
def maze_files_removed() -> Iterator[None]:
    """Build Gymnasium-Robotics maze envs inside this context so their model files do not outlive it.

    Gymnasium-Robotics writes each maze model next to ``tempfile.gettempdir()``; here that is a private
    folder, removed on exit, when MuJoCo has already read the model. Files the caller needs after the
    build (a patched robot model, say) must be written before entering. ``tempfile.tempdir`` is
    process-wide, so do not build envs from several threads at once.
    """
    private = tempfile.mkdtemp(prefix="torchrl_tels_maze_")
    previous, tempfile.tempdir = tempfile.tempdir, private
    try:
        yield
    finally:
        tempfile.tempdir = previous
        shutil.rmtree(private, ignore_errors=True)
