"""Files that appear complete or not at all: write to a temporary name beside the target, then rename.

Every output of svelive goes through :func:`atomic_path` (or :func:`check_output_target`
for the recorder, which appends to its file in place), so one policy holds for all:

* an existing target must be a regular file: a device node (``/dev/null``), a FIFO,
  a socket or a directory is refused with a one-line error and left as it is (a
  rename would replace the node itself with a regular file);
* a symbolic link is refused unless the caller passes ``follow_symlinks=True``: the
  user asks for a link's target by naming the target. When followed, the link's
  final target (which must be a regular file or not exist yet, in an existing
  directory) is replaced atomically in its own directory and the link is kept.

The check and the rename are two system calls: a path swapped for a device node
between them is still replaced. That needs write access to the directory, which
is the access the rename itself needs; the policy is against mistakes, not against
an attacker who already has it.
"""

from __future__ import annotations

import os
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from svelive.core.errors import SveliveError

#: What ``stat.S_IFMT`` of a refused target is called in messages.
_KINDS = {
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFIFO: "a FIFO (named pipe)",
    stat.S_IFSOCK: "a socket",
    stat.S_IFDIR: "a directory",
}


def check_output_target(path: str | os.PathLike, *, follow_symlinks: bool = False) -> Path:
    """The file an output named ``path`` is written to, after checking it may be replaced.

    Args:
        path: the output path the user gave.
        follow_symlinks: when ``path`` is a symbolic link, write to its final target
            instead of refusing.

    Returns:
        ``path`` itself, or with ``follow_symlinks`` the resolved target of a link.

    Raises:
        SveliveError: (one line, naming the fix) when the directory does not exist, or
            ``path`` exists and is not a regular file (device, FIFO, socket, directory),
            or is a symbolic link and ``follow_symlinks`` is False.
    """
    path = Path(path)
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        info = None
    except OSError as exc:
        raise SveliveError(f"{path}: cannot check the output ({exc.strerror})") from None
    if info is not None and stat.S_ISLNK(info.st_mode):
        target = Path(os.path.realpath(path))
        if not follow_symlinks:
            raise SveliveError(f"{path}: is a symbolic link (to {target}); refusing to replace it: give {target} "
                               "itself as the output, or remove the link")
        return check_output_target(target)
    if info is not None and not stat.S_ISREG(info.st_mode):
        kind = _KINDS.get(stat.S_IFMT(info.st_mode), "not a regular file")
        raise SveliveError(f"{path}: is {kind}; an output replaces only a regular file: give a file name")
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise SveliveError(f"{path}: directory {directory} does not exist")
    return path


@contextmanager
def atomic_path(path: str | os.PathLike, *, follow_symlinks: bool = False) -> Iterator[Path]:
    """Yield a temporary path in the target's directory; rename it onto the target on success.

    The target is checked first (:func:`check_output_target`): an existing target that
    is not a regular file, or a symbolic link unless ``follow_symlinks``, is refused
    and left untouched. On any exception the temporary file is removed and the
    target is untouched. The file gets the permissions a new file would (umask applied).
    """
    target = check_output_target(path, follow_symlinks=follow_symlinks)
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        mask = os.umask(0o022)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes_atomic(path: str | os.PathLike, data: bytes, *, follow_symlinks: bool = False) -> Path:
    """Write ``data`` to ``path`` through :func:`atomic_path`, flushed to disk before the rename."""
    with atomic_path(path, follow_symlinks=follow_symlinks) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    return Path(path)
