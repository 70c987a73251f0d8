"""Atomic file writers: data goes to a temporary name in the target's folder and is moved into place when complete.

A reader (or a later run) therefore sees either the previous file or the complete new one, never a half-written
file; an exception while writing removes the temporary file and leaves the previous file untouched.
`os.replace` is atomic on POSIX and Windows when source and target lie in the same folder, which is why the
temporary file is created next to the target.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Literal, overload


def _temp_in(target: Path) -> tuple[int, Path]:
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".partial", dir=target.parent)
    return fd, Path(name)


@overload
@contextlib.contextmanager
def atomic_open(
    path: str | Path, mode: Literal["w"] = "w", *, encoding: str = "utf-8", newline: str | None = None
) -> Iterator[IO[str]]: ...


@overload
@contextlib.contextmanager
def atomic_open(
    path: str | Path, mode: Literal["wb"], *, encoding: str = "utf-8", newline: str | None = None
) -> Iterator[IO[bytes]]: ...


@contextlib.contextmanager
def atomic_open(
    path: str | Path, mode: str = "w", *, encoding: str = "utf-8", newline: str | None = None
) -> Iterator[IO[str]] | Iterator[IO[bytes]]:
    """Open a temporary file next to `path` for writing; on a clean exit it replaces `path`.

    mode: "w" (text, `encoding`, `newline` as for `open`) or "wb". The folder of `path` must exist. On an
    exception inside the block the temporary file is deleted and `path` keeps its previous content (or stays
    absent). The new file gets the permissions a plain `open` would give (0o666 minus the umask).
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open supports modes 'w' and 'wb', got {mode!r}")
    target = Path(path)
    fd, tmp = _temp_in(target)
    try:
        _apply_umask(fd)
        fh: IO[str] | IO[bytes]
        if mode == "wb":
            fh = os.fdopen(fd, "wb")
        else:
            fh = os.fdopen(fd, "w", encoding=encoding, newline=newline)
        with fh:
            yield fh
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` atomically (see `atomic_open`)."""
    with atomic_open(path, "wb") as fh:
        fh.write(data)


def atomic_write_text(path: str | Path, text: str, encoding: str = "utf-8") -> None:
    """Write `text` to `path` atomically in `encoding` (UTF-8 by default)."""
    with atomic_open(path, "w", encoding=encoding, newline="") as fh:
        fh.write(text)


def _apply_umask(fd: int) -> None:
    """mkstemp creates files 0o600; give the file the mode `open()` would (0o666 & ~umask, 0o644 when unknown)."""
    if not hasattr(os, "fchmod"):  # Windows: mkstemp's default is fine
        return
    os.fchmod(fd, 0o666 & ~_umask())


def _umask() -> int:
    """The process umask, read without changing it (Linux /proc); 0o022 elsewhere."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return 0o022
