"""Value equality of artifacts for the tests: NaN equals NaN, nulls must match, types too."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq


def arrays_equal(a: pa.Array, b: pa.Array) -> bool:
    """Whether two arrays hold the same values (NaN equal to NaN), nulls and type."""
    if a.type != b.type or len(a) != len(b) or a.null_count != b.null_count:
        return False
    if a.null_count and not a.is_null().equals(b.is_null()):
        return False
    if pa.types.is_list(a.type) or pa.types.is_large_list(a.type):
        return (pc.list_value_length(a).fill_null(0).equals(
                    pc.list_value_length(b).fill_null(0))
                and arrays_equal(pc.list_flatten(a), pc.list_flatten(b)))
    if pa.types.is_floating(a.type):
        return bool(np.array_equal(a.fill_null(0).to_numpy(zero_copy_only=False),
                                   b.fill_null(0).to_numpy(zero_copy_only=False),
                                   equal_nan=True))
    return bool(a.equals(b))


def table_differences(a: pa.Table, b: pa.Table) -> list[str]:
    """The columns in which two tables differ (empty: value-equal, schema metadata aside)."""
    if a.column_names != b.column_names:
        return [f"columns {a.column_names} vs {b.column_names}"]
    if a.num_rows != b.num_rows:
        return [f"rows {a.num_rows} vs {b.num_rows}"]
    return [name for name in a.column_names
            if not arrays_equal(a.column(name).combine_chunks(), b.column(name).combine_chunks())]


def workdir_differences(a: Path, b: Path) -> dict[str, list[str]]:
    """Every artifact of workdir ``b`` compared with the same one in ``a``."""
    found: dict[str, list[str]] = {}
    for path in sorted(b.glob("*/*.parquet")):
        rel = path.relative_to(b)
        other = a / rel
        found[str(rel)] = (table_differences(pq.read_table(other), pq.read_table(path))
                           if other.exists() else ["missing"])
    return found
