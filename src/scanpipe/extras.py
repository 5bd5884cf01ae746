"""Optional dependencies: import them where a feature needs them, with an install hint.

The core (decode → export) needs only the required packages; acquisition-only and live-only
packages are extras (see pyproject.toml): ``scanpipe[acquire]`` (pyserial, for the serial motor
link) and ``scanpipe[live]`` (foxglove-sdk and websockets, for ``--live``).
"""

from __future__ import annotations

import importlib
from types import ModuleType

from scanpipe.errors import MissingDependencyError

#: import name → (distribution name, extra that installs it).
OPTIONAL: dict[str, tuple[str, str]] = {
    "serial": ("pyserial", "acquire"),
    "foxglove": ("foxglove-sdk", "live"),
    "websockets": ("websockets", "live"),
}


def require(module: str, purpose: str) -> ModuleType:
    """Import the optional ``module`` (a key of :data:`OPTIONAL`), or raise
    :class:`MissingDependencyError` naming the package and the one-line install command.

    >>> require("nonexistent_optional", "testing")  # doctest: +SKIP
    """
    distribution, extra = OPTIONAL[module]
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise MissingDependencyError(
            f"{purpose} needs the optional package {distribution!r} ({err}); install it with: "
            f"pip install 'scanpipe[{extra}]'") from err
