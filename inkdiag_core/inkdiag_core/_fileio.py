"""Temporary files for atomic writes (written, then renamed over the target), with a new file's mode."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

__all__ = ["refuse_to_replace", "temp_beside"]


def temp_beside(path) -> tuple[int, str]:
    """An open temporary file in ``path``'s directory, for ``os.replace(tmp, path)`` once written.

    ``tempfile.mkstemp`` makes it owner-only (0600); it gets the mode ``open`` gives a new file
    instead (0666 less the umask), so that a model or baselines file written by one user can
    be read by a node running as another, as the CSV and YAML files beside it can. Where the
    filesystem refuses the change (some network and FUSE mounts), it stays 0600.

    Returns
    -------
    fd : int
        Open for writing (the caller closes it).
    tmp : str
        Its path.
    """
    path = Path(path)
    refuse_to_replace(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_umask())
    except OSError:  # a filesystem without modes: the file is written all the same
        pass
    return fd, tmp


def refuse_to_replace(path) -> None:
    """Raise :class:`OSError` if ``path`` is, or links to, something that exists and is not a regular file: a
    device such as ``/dev/null``, a pipe, a socket or a directory, which a rename would replace for every user of
    it (``/dev/stdout`` is a link to one). A link to a regular file, or to nothing, may be replaced."""
    path = Path(path)
    if os.path.exists(path) and not os.path.isfile(path):
        kind = "a directory" if path.is_dir() else "not a regular file (a device, pipe or socket)"
        raise OSError(f"{path} is {kind}: a file written there is renamed into place, which would replace "
                      "it; give a file's name")


def _umask() -> int:
    """The process's umask, read from ``/proc`` where the kernel shows it (setting it to read it, the
    fallback, races with other threads creating files)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
