"""Pieces shared by the `sandro-bench` subcommands. Bad arguments or input files raise ValueError (one line)."""

from __future__ import annotations

import csv
import time
from collections.abc import Iterable, Mapping
from pathlib import Path


def default_out_dir(benchmark: str) -> Path:
    """results/<benchmark>/<local time stamp>, relative to the working directory."""
    return Path("results") / benchmark / time.strftime("%Y%m%d-%H%M%S")


def parse_list(text: str, allowed: Iterable[str], what: str) -> list[str]:
    """Split a comma list, keeping the order given; names outside `allowed` are a ValueError."""
    allowed = list(allowed)
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in allowed]
    if unknown or not names:
        raise ValueError(f"unknown or no {what} {','.join(unknown)!r}; choose from {','.join(allowed)}")
    return list(dict.fromkeys(names))


def parse_int_list(text: str, option: str, minimum: int, item: str) -> list[int]:
    """A comma list of integers, each at least `minimum`, in the order given; ValueError naming `option` otherwise."""
    try:
        values = [int(value) for value in text.split(",")]
    except ValueError:
        raise ValueError(f"{option} {text!r}: expected a comma list of integers") from None
    if min(values) < minimum:
        raise ValueError(f"{option}: every {item} must be at least {minimum}")
    return values


def write_csv(path: Path, rows: Iterable[Mapping[str, object]], fields: list[str]) -> None:
    """Write dict rows with the given columns (floats with up to 6 significant digits)."""
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: f"{v:.6g}" if isinstance(v, float) else v for k, v in row.items()})
