"""scanpipe: a 2-D laser scanner on a stepper turntable plus a camera, to a textured 3-D model.

The public Python API (see docs/api.md), imported on first use so that ``import scanpipe`` stays
light (no numpy, pyarrow or Open3D until a function is called):

- :func:`read_recording`: a recording (MCAP), read tolerantly, as numpy arrays and messages;
- :func:`read_catalogue`: any MCAP file's channels, schemas, counts and time range;
- :func:`recover_mcap`: every readable message of a damaged MCAP file into a new one;
- :func:`run`: the cached chain (decode → … → export) from a recording into a workdir;
- :func:`registry` and :func:`get_stage`: the stages, each runnable in memory
  (``get_stage("decode").run({"recording": path}).tables``);
- :class:`ScanpipeError`: the root of every error meant for a user.
"""

from __future__ import annotations

import importlib
import os
from importlib.metadata import PackageNotFoundError, version
from typing import Any

# Arrow's allocator (mimalloc) hands freed pages back to the system only after a delay, and
# Arrow's release_unused does not shorten it: a table released between stages stayed resident
# and a Parquet read peaked at twice its table (the lab chain's peak 2.52 → 2.16 GB without
# the delay; docs/performance.md). Read when pyarrow is first loaded: a user's setting wins.
os.environ.setdefault("MIMALLOC_PURGE_DELAY", "0")

from scanpipe.lazy_open3d import defer_plotly_viewer

# Open3D's plotly/dash viewer (~0.45 s of CPU per process) loads only if someone calls it
defer_plotly_viewer()

try:
    __version__ = version("scanpipe")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0"

#: Public name → the module that defines it (imported when the name is first used). Named as
#: strings, not imported under TYPE_CHECKING: every module imports ``__version__`` from here, so
#: an import back would be a circle (tests/test_contracts.py).
_LAZY = {
    "read_recording": "scanpipe.recording.reader",
    "read_catalogue": "scanpipe.recording.reader",
    "recover_mcap": "scanpipe.recording.catalogue",
    "run": "scanpipe.api",
    "registry": "scanpipe.stages",
    "get_stage": "scanpipe.stages",
    "ScanpipeError": "scanpipe.errors",
}

__all__ = ["ScanpipeError", "__version__", "get_stage", "read_catalogue", "read_recording",
           "recover_mcap", "registry", "run"]


def __getattr__(name: str) -> Any:
    """Import a public name on first use (PEP 562)."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'scanpipe' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
