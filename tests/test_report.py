"""``scanpipe report``: one self-contained HTML file with counts, plots, previews, evaluation."""

from __future__ import annotations

import re
from collections.abc import Callable
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from result_tables import points_table, textured_quad

from scanpipe.artifacts import write_artifact
from scanpipe.exporters.glb import glb_bytes
from scanpipe.exporters.model import mesh_from_tables
from scanpipe.report import sync_residuals


class _References(HTMLParser):
    """Every URL-carrying attribute and every tag name of a document."""

    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []
        self.tags: set[str] = set()

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.add(tag)
        self.urls += [v or "" for k, v in attrs if k in ("src", "href", "data", "srcset")]


def _profiles(n: int = 40, jitter_ms: float = 0.3) -> pa.Table:
    rng = np.random.default_rng(0)
    device = np.arange(n, dtype=np.int64) * 200_000_000
    recv = 1_700_000_000_000_000_000 + device + 2_000_000 + (
        rng.normal(0, jitter_ms, n) * 1e6).astype(np.int64)
    return pa.table({"recv_time_ns": recv, "device_time_ns": device,
                     "ranges_m": pa.array([[1.0, 2.0]] * n, pa.list_(pa.float32()))})


def _workdir(root: Path) -> Path:
    def put(stage: str, name: str, table: pa.Table, report: dict, seconds: float) -> None:
        write_artifact(root / stage / f"{name}.parquet", table,
                       {"stage": stage, "key": f"key-{stage}", "seconds": seconds,
                        "rows": table.num_rows, "report": report})

    put("decode", "profiles", _profiles(), {"dialect": "ldoem", "counts": {"profiles": 40},
                                             "counters": {"checksum_failures": 2}}, 0.8)
    put("assemble", "points", points_table(), {"points": 60, "profiles_used": 6}, 0.4)
    put("filter", "points", points_table(profiles=4),
        {"points_in": 60, "points_out": 40, "filters": {"range": {"taken": 20}}}, 0.2)
    quad = textured_quad()
    for name in ("mesh_vertices", "mesh_faces"):
        put("mesh", name, quad[name], {"faces": 2}, 1.0)
    for name in ("textured_faces", "texture_pages"):
        put("texture", name, quad[name], {"pages": 1}, 2.0)
    return root


@pytest.mark.slow
def test_report_is_one_self_contained_file(cli: Callable, tmp_path: Path) -> None:
    work = _workdir(tmp_path / "w")
    truth = work / "truth"
    truth.mkdir()
    quad = textured_quad()
    (truth / "scene.glb").write_bytes(glb_bytes(mesh_from_tables(
        quad["mesh_vertices"], quad["mesh_faces"], quad["textured_faces"],
        quad["texture_pages"])))
    before = {p for p in tmp_path.rglob("*")}
    result = cli("report", work, "--out", tmp_path / "report.html")
    assert result.code == 0, result.err
    assert {p for p in tmp_path.rglob("*")} - before == {tmp_path / "report.html"}
    text = (tmp_path / "report.html").read_text()
    parser = _References()
    parser.feed(text)
    assert parser.urls and all(u.startswith("data:image/png;base64,") for u in parser.urls)
    assert not parser.tags & {"link", "iframe", "object", "embed"}
    assert not re.search(r"url\(", text)
    order = ("At a glance", "Previews", "Evaluation against ground truth", "Points",
             "Time synchronisation", "Stage times", "Details")
    for heading in order:
        assert f"<h2>{heading}</h2>" in text, heading
    # Headline and pictures first, the raw per-stage reports last.
    positions = [text.index(f"<h2>{heading}</h2>") for heading in order]
    assert positions == sorted(positions)
    for caption in ("Range histogram", "Coverage over α × β", "Seconds per stage",
                    "Receive-time residuals", "plan", "panorama"):
        assert caption in text, caption
    assert "checksum_failures" in text and "points_out" in text
    assert "fscore" in text and "texture_psnr_db" in text
    assert len(parser.urls) >= 7  # 4 plots + 3 previews


def test_report_without_mesh_or_truth_still_works(cli: Callable, tmp_path: Path) -> None:
    work = tmp_path / "w"
    write_artifact(work / "points.parquet", points_table(), {"stage": "assemble", "seconds": 1})
    result = cli("report", work)
    assert result.code == 0, result.err
    text = (work / "report.html").read_text()
    assert "Range histogram" in text and "<h2>Previews</h2>" not in text
    assert "Evaluation" not in text


def test_report_errors(cli: Callable, tmp_path: Path) -> None:
    result = cli("report", tmp_path / "missing")
    assert result.code == 2 and "not a folder" in result.err
    result = cli("report", tmp_path)
    assert result.code == 1 and "no scanpipe artifacts" in result.err


def test_sync_residuals_measure_jitter_and_drift() -> None:
    png, stats = sync_residuals(_profiles(400, jitter_ms=0.5)) or (b"", {})
    assert png.startswith(b"\x89PNG")
    assert 0.4 < stats["rms_ms"] < 0.6
    assert abs(stats["drift_ppm"]) < 50
    no_device = pa.table({"recv_time_ns": [1, 2, 3],
                          "device_time_ns": pa.array([None, None, None], pa.int64())})
    assert sync_residuals(no_device) is None
