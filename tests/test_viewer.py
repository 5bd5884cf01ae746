"""The 3-D viewer: in the report and served by ``scanpipe view``, rendered by a real headless
Chromium (Debian's, driven by Playwright) that must find the textured model on the canvas."""

from __future__ import annotations

import io
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from playwright.sync_api import Browser, Page, sync_playwright
from result_tables import textured_box

from scanpipe.artifacts import write_artifact
from scanpipe.viewer import make_server

CHROMIUM = Path("/usr/bin/chromium")
BACKGROUND = np.array([0xF4, 0xF4, 0xF4])


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    assert CHROMIUM.is_file(), "Debian's chromium is needed (./run.sh test installs it)"
    with sync_playwright() as playwright:
        # SwiftShader gives WebGL without a GPU.
        browser = playwright.chromium.launch(
            executable_path=str(CHROMIUM),
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
        yield browser
        browser.close()


@pytest.fixture
def workdir(tmp_path: Path) -> Path:
    root = tmp_path / "work"
    for name, table in textured_box().items():
        stage = "mesh" if name.startswith("mesh") else "texture"
        write_artifact(root / stage / f"{name}.parquet", table,
                       {"stage": stage, "key": f"{stage}-key", "seconds": 0.1,
                        "rows": table.num_rows, "report": {}})
    return root


def rendered(page: Page, url: str) -> tuple[str, np.ndarray]:
    """The viewer's state once it settles, and the canvas as an RGB array."""
    page.goto(url)
    page.wait_for_function("['ready', 'error'].includes(document.body.dataset.viewer)",
                           timeout=60_000)
    png = page.locator("#scanpipe-viewer-canvas").screenshot()
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
    return str(page.evaluate("document.body.dataset.viewer")), rgb


def model_share(rgb: np.ndarray) -> float:
    """The share of the canvas that is not background."""
    return float(np.mean(np.abs(rgb - BACKGROUND).max(axis=2) > 24))


def has_texture_colours(rgb: np.ndarray) -> bool:
    """The box's texture is red, green and blue quadrants: all three must be drawn."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    red = np.mean((r > 150) & (g < 90) & (b < 90))
    green = np.mean((g > 150) & (r < 90) & (b < 90))
    blue = np.mean((b > 120) & (r < 90) & (g < 90))
    return bool(min(red, green, blue) > 0.005)


def test_the_report_shows_the_textured_model(cli: Callable, workdir: Path,
                                             browser: Browser) -> None:
    result = cli("report", str(workdir))
    assert result.code == 0, result.err
    html = (workdir / "report.html").read_text()
    assert "<h2>3-D view</h2>" in html and "http://" not in html.split("<h2>3-D view")[1][:2000]
    page = browser.new_page(viewport={"width": 1000, "height": 800})
    state, rgb = rendered(page, (workdir / "report.html").as_uri())
    assert state == "ready", page.inner_text("#scanpipe-viewer-status")
    info = page.evaluate("window.scanpipeViewerInfo")
    assert info["triangles"] == 12 and info["textured"] is True
    # The page's model is Draco-compressed; three.js decoded it to the box's true extent.
    assert "KHR_draco_mesh_compression" in html
    np.testing.assert_allclose(info["min"], [-2.0, -1.2, -2.5], atol=1e-3)
    np.testing.assert_allclose(info["max"], [2.0, 1.8, 2.5], atol=1e-3)
    assert model_share(rgb) > 0.1
    assert has_texture_colours(rgb)
    # From the scanner's place (inside the box) the faces towards it are drawn, not culled.
    page.click("#scanpipe-view-inside")
    png = page.locator("#scanpipe-viewer-canvas").screenshot()
    inside = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
    # (white texture quadrants read as background, so not all of it counts)
    assert model_share(inside) > 0.6 and has_texture_colours(inside)
    page.close()


def test_a_page_without_its_model_is_found_blank(workdir: Path, browser: Browser,
                                                 tmp_path: Path) -> None:
    """The check above can fail: the same page with the model taken out draws nothing."""
    from scanpipe.report import write_report

    html = write_report(workdir, tmp_path / "r.html").read_text()
    start = html.index('<script id="scanpipe-model"')
    start = html.index(">", start) + 1
    broken = tmp_path / "broken.html"
    broken.write_text(html[:start] + html[html.index("</script>", start):])
    page = browser.new_page()
    state, rgb = rendered(page, broken.as_uri())
    assert state == "error"
    assert "no model" in page.inner_text("#scanpipe-viewer-status")
    assert model_share(rgb) < 0.01 and not has_texture_colours(rgb)
    page.close()


def test_scanpipe_view_serves_the_model(workdir: Path, browser: Browser) -> None:
    server = make_server(workdir)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        page = browser.new_page()
        state, rgb = rendered(page, f"http://127.0.0.1:{server.server_address[1]}/")
        assert state == "ready"
        assert model_share(rgb) > 0.1 and has_texture_colours(rgb)
        page.close()
    finally:
        server.shutdown()
        server.server_close()


def test_plain_and_draco_models_draw_alike(workdir: Path, browser: Browser,
                                           tmp_path: Path) -> None:
    """The same model, uncompressed and Draco-compressed, gives the same extent, triangle
    count and picture (within the 16-bit quantum and a few pixels of rasterisation)."""
    from scanpipe.viewer import model_glb, viewer_page

    pictures, infos = [], []
    for draco in (False, True):
        glb = model_glb(workdir, draco=draco)
        assert (b"KHR_draco_mesh_compression" in glb) is draco
        page_file = tmp_path / f"draco{draco}.html"
        page_file.write_text(viewer_page("model", glb=glb))
        page = browser.new_page(viewport={"width": 640, "height": 480})
        state, rgb = rendered(page, page_file.as_uri())
        assert state == "ready", page.inner_text("#scanpipe-viewer-status")
        infos.append(page.evaluate("window.scanpipeViewerInfo"))
        pictures.append(rgb)
        page.close()
    assert infos[0]["triangles"] == infos[1]["triangles"] == 12
    np.testing.assert_allclose(infos[0]["min"], infos[1]["min"], atol=1e-3)
    np.testing.assert_allclose(infos[0]["max"], infos[1]["max"], atol=1e-3)
    differing = np.mean(np.abs(pictures[0] - pictures[1]).max(axis=2) > 40)
    assert differing < 0.01 and has_texture_colours(pictures[1])


def test_report_without_viewer_has_no_script(cli: Callable, workdir: Path) -> None:
    assert cli("report", str(workdir), "--no-viewer").code == 0
    assert "<script" not in (workdir / "report.html").read_text()


def test_view_refuses_a_folder_without_a_mesh(cli: Callable, tmp_path: Path) -> None:
    result = cli("view", str(tmp_path / "missing"), "--no-browser")
    assert result.code == 2 and "not a folder" in result.err
    (tmp_path / "empty").mkdir()
    result = cli("view", str(tmp_path / "empty"), "--no-browser")
    assert result.code != 0 and "no artifacts" in result.err
    assert len(result.err.strip().splitlines()) == 1
