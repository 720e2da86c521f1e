"""Checks of output files (USD recordings, image grids) before any work is done, so that a long run never ends in an
unwritable path. Folders are created only when the caller asks for it."""

from __future__ import annotations

import os
from pathlib import Path


def check_output_path(path: str | os.PathLike, what: str, make_dirs: bool = False) -> Path:
    """Raise ``ValueError`` unless a file can be written at ``path``; return it as a ``Path``.

    Args:
        path: the file to be written later.
        what: the name of the output in messages (``"--usd"``, ``"USD path"``).
        make_dirs: create the missing folders of ``path`` (otherwise a missing folder is an error).
    """
    out = Path(path).expanduser()
    if out.name in ("", ".", ".."):
        raise ValueError(f"{what} {str(path)!r} names a folder, not a file")
    if out.is_dir():
        raise ValueError(f"{what} {str(out)!r} is a folder, not a file")
    parent = out.parent
    if not parent.exists():
        if not make_dirs:
            raise ValueError(f"{what}: the folder {str(parent)!r} does not exist (create it first, or ask for missing "
                             "folders to be created)")
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"{what}: cannot create the folder {str(parent)!r} ({exc.strerror})") from None
    if not parent.is_dir():
        raise ValueError(f"{what}: {str(parent)!r} is not a folder")
    if out.exists() and not os.access(out, os.W_OK):
        raise ValueError(f"{what}: {str(out)!r} exists and is not writable")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"{what}: the folder {str(parent)!r} is not writable")
    return out
