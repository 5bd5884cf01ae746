"""The functions of the public API that are not another module's (see :mod:`scanpipe`)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from scanpipe.pipeline import RunRecord, run_chain, validate_pipeline_params
from scanpipe.progress import ProgressFn, no_progress
from scanpipe.stages import chain_stages


def run(recording: Path | str, workdir: Path | str,
        params: Mapping[str, Mapping[str, Any]] | None = None, to: str | None = None,
        force: bool = False, progress: ProgressFn = no_progress) -> list[RunRecord]:
    """Run the chain from a recording into ``workdir`` (what ``scanpipe run`` does), reusing
    every stage whose inputs and parameters are unchanged.

    ``params`` is ``{stage: {key: value}}`` (nested keys as nested dicts), validated all at once
    (unknown stages or keys are a :class:`~scanpipe.errors.ParameterError` listing every
    problem); ``to`` stops after that stage. Returns one :class:`~scanpipe.pipeline.RunRecord`
    per stage (its outputs, key, report and whether it was reused).

    Example (``scanpipe simulate --direct --out scan.mcap --truth truth`` makes a recording)::

        records = run("scan.mcap", "work", {"mesh": {"method": "grid"}}, to="mesh")
        [r.stage for r in records]  # ['decode', 'assemble', 'filter', 'mesh']
    """
    chain = chain_stages("recording")
    validated = validate_pipeline_params(chain, {k: dict(v) for k, v in (params or {}).items()},
                                         "run()")
    return run_chain(Path(recording), Path(workdir), validated, chain, to=to, force=force,
                     progress=progress)
