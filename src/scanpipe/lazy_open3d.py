"""Open3D without its plotly/dash viewer at import time.

``import open3d`` (0.18–0.20) imports ``open3d.visualization.draw_plotly``, which imports plotly
and dash: about half of Open3D's import (~0.45 s of CPU of ~0.95 s measured), paid by every
command and every batch or Ray worker that touches Open3D, for a viewer scanpipe never uses.
:func:`defer_plotly_viewer` puts a stand-in for that module into ``sys.modules`` before Open3D
is imported: its three public functions (``get_plotly_fig``, ``draw_plotly``,
``draw_plotly_server``) and any other name load the real module on first use, so a notebook
calling ``open3d.visualization.draw_plotly(...)`` still gets the real viewer.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
import types
from collections.abc import Callable
from typing import Any

#: The Open3D module that imports plotly and dash.
PLOTLY_MODULE = "open3d.visualization.draw_plotly"
#: What ``open3d.visualization`` imports from it by name.
PROXIED = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def real_plotly_module() -> types.ModuleType:
    """The real ``open3d.visualization.draw_plotly``, loaded now if the stand-in holds its
    place (plotly and dash are imported then)."""
    current = sys.modules.get(PLOTLY_MODULE)
    if current is not None and not getattr(current, "_scanpipe_stand_in", False):
        return current
    import open3d.visualization

    spec = importlib.machinery.PathFinder.find_spec(PLOTLY_MODULE,
                                                   list(open3d.visualization.__path__))
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot find {PLOTLY_MODULE}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[PLOTLY_MODULE] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        if current is not None:
            sys.modules[PLOTLY_MODULE] = current
        raise
    return module


def _proxy(name: str) -> Callable[..., Any]:
    def call(*args: Any, **kwargs: Any) -> Any:
        return getattr(real_plotly_module(), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    call.__doc__ = f"Open3D's ``{name}`` (its module, plotly and dash load on first call)."
    return call


def defer_plotly_viewer() -> bool:
    """Put the stand-in in place when Open3D is not imported yet; True when it was put."""
    if "open3d" in sys.modules or PLOTLY_MODULE in sys.modules:
        return False
    stand_in = types.ModuleType(PLOTLY_MODULE, __doc__)
    stand_in._scanpipe_stand_in = True  # type: ignore[attr-defined]
    for name in PROXIED:
        setattr(stand_in, name, _proxy(name))

    def attribute(name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(real_plotly_module(), name)

    stand_in.__getattr__ = attribute  # type: ignore[method-assign]
    sys.modules[PLOTLY_MODULE] = stand_in
    return True
