"""How many threads a piece of work may use: the one reading of ``OMP_NUM_THREADS``."""

from __future__ import annotations

import os


def omp_threads() -> int | None:
    """``OMP_NUM_THREADS`` when it is a positive whole number (a batch worker's share of the
    cores, or the user's own limit), else None: the caller then decides from the CPU count."""
    given = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(given) if given.isdigit() and int(given) > 0 else None
