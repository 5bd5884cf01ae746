"""Open3D imported after scanpipe leaves plotly and dash out until its plotly viewer is used
(scanpipe.lazy_open3d), and the viewer still works then."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

PROGRAM = """
import sys
import scanpipe, open3d, numpy as np
assert "dash" not in sys.modules and "plotly" not in sys.modules, "plotly imported with open3d"
cloud = open3d.geometry.PointCloud(open3d.utility.Vector3dVector(np.zeros((4, 3))))
figure = open3d.visualization.get_plotly_fig([cloud])
assert type(figure).__name__ == "Figure" and "dash" in sys.modules
from open3d.visualization.draw_plotly import get_point_object  # any other name: the real one
assert get_point_object.__module__ == "open3d.visualization.draw_plotly"
print("ok")
"""


def test_open3d_after_scanpipe_defers_plotly_and_dash() -> None:
    result = subprocess.run([sys.executable, "-c", PROGRAM], capture_output=True, text=True,
                            env={"PYTHONPATH": str(SRC), "OMP_NUM_THREADS": "1"}, timeout=120,
                            check=False)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr


def test_an_open3d_imported_first_is_left_alone() -> None:
    program = ("import sys, open3d, scanpipe\n"
               "from scanpipe.lazy_open3d import PLOTLY_MODULE, defer_plotly_viewer\n"
               "assert not defer_plotly_viewer()\n"
               "assert not getattr(sys.modules[PLOTLY_MODULE], '_scanpipe_stand_in', False)\n"
               "print('ok')")
    result = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True,
                            env={"PYTHONPATH": str(SRC), "OMP_NUM_THREADS": "1"}, timeout=120,
                            check=False)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr
