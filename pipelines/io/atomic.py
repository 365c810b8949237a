"""Output that appears whole or not at all: files and folders written under a temporary name beside the target and
renamed into place only on success; and a new timestamped results folder per run, with a `latest` link to it."""

from __future__ import annotations

import os
import shutil
import tempfile
import time
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


def new_run_folder(base: str | Path) -> Path:
    """Create base/<YYYYmmdd-HHMMSS>[-k], never reusing an existing folder.

    Raises:
        OSError: `base` cannot be created or written.
    """
    base = Path(base)
    base.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    for attempt in range(1000):
        folder = base / (stamp if attempt == 0 else f"{stamp}-{attempt}")
        try:
            folder.mkdir()
        except FileExistsError:
            continue
        return folder
    raise OSError(f"{base}: could not create a new results folder")


def link_latest(folder: Path) -> Path:
    """Point folder.parent/latest at `folder` (a relative symbolic link, replaced atomically)."""
    link = folder.parent / "latest"
    tmp = folder.parent / f".latest.tmp-{os.getpid()}"
    if tmp.is_symlink() or tmp.exists():
        tmp.unlink()
    tmp.symlink_to(folder.name, target_is_directory=True)
    os.replace(tmp, link)
    return link
