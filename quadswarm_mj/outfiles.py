"""Output files that a failed command never destroys: a writability check to run before the work, and
atomic writes (a temporary file in the target's directory, then ``os.replace``), so the target holds
either its old bytes or the complete new ones, never a truncated mix.

Targets that exist and are not regular files (``/dev/stdout``, a FIFO) are written in place: they
cannot be replaced, and replacing them would destroy the device node or link.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import stat
from collections.abc import Iterator
from pathlib import Path


def _target(path: str | os.PathLike) -> Path:
    """The file a write to ``path`` lands in: symlinks resolved, so a link keeps pointing at the new file."""
    return Path(os.path.realpath(os.fspath(path)))


def _in_place(target: Path) -> bool:
    """True for an existing target that is not a regular file (written in place, not replaced)."""
    try:
        return not stat.S_ISREG(os.stat(target).st_mode)
    except OSError:  # missing, or below a missing directory or a file
        return False


def check_writable(path: str | os.PathLike, what: str = "output file", make_parents: bool = False) -> Path:
    """Raise ``ValueError`` naming ``what`` and the reason unless a file can be written at ``path``.

    Run it before the work: it creates (``make_parents``) the missing directories and a probe file
    in the target's directory, which it removes. Returns ``path`` as a ``Path``."""
    p = Path(path)
    target = _target(p)
    if target.is_dir():
        raise ValueError(f"cannot write {what} {str(p)!r}: it is a directory")
    if _in_place(target):
        if not os.access(target, os.W_OK):
            raise ValueError(f"cannot write {what} {str(p)!r}: permission denied")
        return p
    parent = target.parent
    if make_parents:
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ValueError(f"cannot write {what} {str(p)!r}: cannot create its directory "
                             f"({e.strerror or e})") from None
    if not parent.is_dir():
        reason = "is not a directory" if parent.exists() else "does not exist"
        raise ValueError(f"cannot write {what} {str(p)!r}: {str(parent)!r} {reason}")
    try:
        probe = _new_temp(target)
    except OSError as e:
        raise ValueError(f"cannot write {what} {str(p)!r}: {e.strerror or e}") from None
    probe.unlink()
    return p


def _new_temp(target: Path) -> Path:
    """Create an empty, new, hidden file beside ``target`` (same suffix, mode 0666 less the umask)."""
    for _ in range(100):
        tmp = target.parent / f".{target.stem}.{secrets.token_hex(4)}.tmp{target.suffix}"
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except FileExistsError:
            continue
        return tmp
    raise FileExistsError(f"no free temporary name beside {str(target)!r}")  # pragma: no cover


@contextlib.contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """Context manager yielding a temporary path beside ``path`` (same suffix) to write; on a clean exit
    it replaces ``path`` with it (keeping an existing file's permission bits), on an exception it is
    removed and ``path`` is untouched. For an existing non-regular target it yields ``path`` itself."""
    target = _target(path)
    if _in_place(target):
        yield target
        return
    tmp = _new_temp(target)
    try:
        yield tmp
        with contextlib.suppress(FileNotFoundError):  # keep an existing file's permission bits
            os.chmod(tmp, stat.S_IMODE(os.stat(target).st_mode))
        os.replace(tmp, target)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file, fsync, ``os.replace``)."""
    target = _target(path)
    if _in_place(target):  # /dev/stdout, a FIFO: written as they are
        with open(target, "wb") as f:
            f.write(data)
        return
    with replacing(target) as tmp, open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())  # the bytes are on disk before the name points at them


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))
