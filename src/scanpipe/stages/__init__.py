"""The stages, one module each, and the registry that declares them in pipeline order.

Add a stage here and nowhere else: the runner's chain (:func:`chain_stages`), ``scanpipe
stages``, the workdir's stage order and provenance all derive from :func:`registry`.
"""

from __future__ import annotations

from scanpipe.errors import ArtifactError
from scanpipe.stage import RAW_INPUTS, Stage
from scanpipe.stages import (
    assemble,
    calibrate,
    decode,
    export,
    filter,
    import_points,
    import_profiles,
    mesh,
    texture,
)

#: Every stage in pipeline order (import-points stands beside decode: both make the first
#: artifacts, from a recording or from another tool's point file).
STAGES: tuple[Stage, ...] = (decode.STAGE, import_points.STAGE, import_profiles.STAGE,
                             calibrate.STAGE, assemble.STAGE, filter.STAGE,
                             mesh.STAGE, texture.STAGE, export.STAGE)


def registry() -> dict[str, Stage]:
    """Every stage by name, in pipeline order."""
    return {s.name: s for s in STAGES}


def get_stage(name: str) -> Stage:
    """The stage called ``name``."""
    stages = registry()
    if name not in stages:
        raise ArtifactError(f"unknown stage {name!r}; stages: {', '.join(stages)}")
    return stages[name]


def chain_stages(source: str = "recording") -> list[Stage]:
    """The stages ``scanpipe run`` chains from a raw ``source``: each whose inputs the source
    or an earlier stage of the chain provides, in pipeline order."""
    available = {source}
    chain = []
    for stage in STAGES:
        raw = [n for n in stage.inputs if n in RAW_INPUTS]
        if all(n in available for n in stage.inputs) and all(n == source for n in raw):
            chain.append(stage)
            available.update(stage.outputs)
    return chain
