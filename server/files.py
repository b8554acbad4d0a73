"""Files the server reads or writes on a client's behalf: only from configured directories, only regular files
of bounded size, opened without ever blocking.

A path a client names (a tone CSV in a configuration, a labscript shot file) is resolved (symbolic links
followed) and must lie inside the directory ``llrs serve`` was given for that kind of file; without such a
directory the server opens none. The file is opened non-blocking, so a FIFO or a device cannot hang the
thread that opens it, and it is checked *on the open descriptor* (``fstat``) to be a regular file no larger
than its kind allows, so it cannot be swapped for something else between the check and the read. Error
messages name the path the client gave and what is wrong with it, never what the file holds.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

__all__ = ["FileRefused", "confine", "open_regular"]


class FileRefused(ValueError):
    """A client-named path the server will not open; the message says why and what is allowed."""


def _shown(path: str | Path) -> str:
    text = str(path)
    return repr(text if len(text) <= 200 else text[:200] + "...")


def confine(path: str | Path, directory: Path | None, *, what: str, option: str) -> Path:
    """``path`` (relative paths are taken inside ``directory``) resolved, if it lies inside ``directory``.

    ``what`` names the kind of file and ``option`` the ``llrs serve`` option that sets the directory, for the
    message when the path is refused.
    """
    if directory is None:
        raise FileRefused(
            f"{what} {_shown(path)}: this server opens no {what}s named by a client; "
            f"start `llrs serve` with {option} DIR and put them in DIR"
        )
    root = directory.resolve()
    resolved = (root / path).resolve()
    if not resolved.is_relative_to(root):
        raise FileRefused(f"{what} {_shown(path)} is outside {root} ({option}); put it in that directory")
    return resolved


def open_regular(path: str | Path, *, what: str, max_bytes: int, write: bool = False) -> BinaryIO:
    """Open ``path`` (``rb``, or ``r+b`` with ``write``) if it is a regular file of at most ``max_bytes``.

    Raises ``FileNotFoundError`` when there is no such file and ``FileRefused`` for anything else wrong.
    """
    flags = (os.O_RDWR if write else os.O_RDONLY) | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise
    except OSError as err:
        raise FileRefused(f"{what} {_shown(path)}: cannot open it ({err.strerror})") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise FileRefused(f"{what} {_shown(path)} is not a regular file")
        if info.st_size > max_bytes:
            raise FileRefused(
                f"{what} {_shown(path)} is {info.st_size} bytes; at most {max_bytes} bytes are accepted"
            )
        os.set_blocking(fd, True)
        return os.fdopen(fd, "r+b" if write else "rb")
    except BaseException:
        os.close(fd)
        raise
