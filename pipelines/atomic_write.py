"""Atomic file output: write to a temporary name beside the target, rename into place only on success."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write `path` through; it replaces `path` when the block ends without error
    and is removed otherwise, so no half-written `path` is ever seen. The temporary keeps the suffix (writers
    such as Open3D and matplotlib choose the format by it)."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write `text` to `path` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


@contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield a path (not yet existing, with the same name as `path`) to build a folder at; it replaces `path`
    (file or folder) when the block ends without error and is removed otherwise. It lies in a hidden
    temporary folder beside `path`, so writers that name inner files after their folder get the final names."""
    path = Path(path)
    staging = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
    try:
        built = staging / path.name
        yield built
        if path.exists() or path.is_symlink():
            os.replace(path, staging / "replaced")  # a folder cannot be renamed over a non-empty one
        os.replace(built, path)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
