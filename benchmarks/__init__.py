"""The benchmarks (``python -m benchmarks``; see docs/performance.md)."""

# scanpipe first, before anything loads pyarrow: it sets Arrow's allocator up (no purge delay:
# freed tables leave the process at once), which a process that loaded pyarrow first keeps
# as it was — the chain-memory figures would then not be a user's ``scanpipe run``.
import scanpipe  # noqa: F401
