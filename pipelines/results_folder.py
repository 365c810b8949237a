"""Results folders: a new timestamped folder per run under a base folder, and a `latest` link to it."""

from __future__ import annotations

import os
import time
from pathlib import Path


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
