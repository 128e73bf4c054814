"""Shared pieces of the readers and writers: errors, atomic writes."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["FormatError", "atomic_write", "atomic_path"]


class FormatError(ValueError):
    """A file does not hold what its format promises.

    The message names the file, the line or field, and what was expected::

        scan000.3d, line 5: expected 3 numbers (x y z), got '1.0 2.0'
    """

    def __init__(self, path: str | os.PathLike, problem: str, *, where: str | None = None) -> None:
        self.path = Path(path)
        self.where = where
        self.problem = problem
        location = f"{self.path}, {where}" if where else f"{self.path}"
        super().__init__(f"{location}: {problem}")


def _umask() -> int:
    """The process's file-creation mask (reading it means setting it; set it straight back)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    Use for writers that need a file name (``np.savez``, ``cv2.imwrite``,
    third-party writers). On any error the temporary file is removed and
    ``path`` is left untouched, so no half-written output ever appears.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=suffix if suffix is not None else "".join(path.suffixes) or ".tmp",
        dir=path.parent,
    )
    os.close(handle)
    temporary_path = Path(temporary)
    try:
        yield temporary_path
        # mkstemp creates the file private (0600); the output gets the permissions any new file would.
        os.chmod(temporary_path, 0o666 & ~_umask())
        os.replace(temporary_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            temporary_path.unlink()
        raise


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator:
    """Open a temporary file beside ``path`` for writing; rename on success."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write mode must be 'w' or 'wb', got {mode!r}")
    with atomic_path(path) as temporary:
        with open(temporary, mode, **({"encoding": "utf-8", "newline": "\n"} if mode == "w" else {})) as stream:
            yield stream
