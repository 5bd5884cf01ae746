"""The interactive 3-D view of a workdir's model: in the report, and served by ``scanpipe view``.

The page runs three.js with its glTF loader and orbit controls, bundled into one script
(``assets/viewer.bundle.js``, built from ``js/viewer.js`` by ``js/build.sh`` and committed), so
the view works offline: no network, no CDN. The model is the same GLB that ``scanpipe export -f
glb --draco`` writes (geometry Draco-compressed; the decoder is bundled too), made from the
workdir's mesh and texture artifacts.

The report holds the model inside the page (base64); ``scanpipe view`` serves it beside the page
from a local HTTP server, so large models need not be inlined.
"""

from __future__ import annotations

import base64
import html
import http.server
import json
import threading
import webbrowser
from functools import lru_cache
from importlib import resources
from pathlib import Path

from scanpipe.errors import ArtifactError, UsageError

#: Models larger than this are not inlined into the report (the page would grow past what a
#: browser opens comfortably); ``scanpipe view`` serves any size.
MAX_INLINE_GLB_BYTES = 64 * 1024 * 1024

_CSS = """
.scanpipe-viewer { position: relative; width: 100%; height: 560px; border: 1px solid #ddd;
  background: #f4f4f4; }
.scanpipe-viewer canvas { width: 100%; height: 100%; display: block; touch-action: none; }
.scanpipe-viewer .bar { position: absolute; left: .5em; top: .5em; display: flex; gap: .4em;
  align-items: center; font: 13px system-ui, sans-serif; color: #444; }
.scanpipe-viewer button { font: inherit; padding: .15em .6em; }
"""


@lru_cache(maxsize=1)
def viewer_script() -> str:
    """The bundled viewer (three.js included), as JavaScript text."""
    asset = resources.files("scanpipe.viewer").joinpath("assets/viewer.bundle.js")
    return asset.read_text(encoding="utf-8")


def model_glb(workdir: Path, draco: bool = True) -> bytes:
    """The workdir's textured model as GLB bytes (the same as ``export -f glb``, with
    ``draco`` as ``--draco``: the page decodes it with the bundled decoder and is about three
    times smaller)."""
    from scanpipe.artifacts import file_bytes
    from scanpipe.exporting import load_tables
    from scanpipe.stages.export import export_files

    if not workdir.is_dir():
        raise UsageError(f"{workdir}: not a folder (give a workdir or a folder of artifacts)")
    files = export_files(load_tables(workdir, "glb"), "glb", "model", draco=draco)
    return file_bytes(files["model.glb"])


def _inline_script(text: str) -> str:
    # A script element ends at the first "</script": never let the text contain one.
    return text.replace("</script", "<\\/script").replace("<!--", "<\\!--")


def viewer_fragment(glb: bytes | None = None, glb_url: str | None = None) -> str:
    """The viewer's HTML: a canvas, two view buttons, the model (inline or by URL), the script.

    Give exactly one of ``glb`` (inlined as base64) and ``glb_url`` (fetched by the page).
    """
    if (glb is None) == (glb_url is None):
        raise ValueError("give exactly one of glb and glb_url")
    if glb is not None:
        payload = base64.b64encode(glb).decode("ascii")
        model = f'<script id="scanpipe-model" type="application/octet-stream">{payload}</script>'
        options = '{canvasId: "scanpipe-viewer-canvas", glbElementId: "scanpipe-model"}'
    else:
        model = ""
        url = html.escape(str(glb_url), quote=True).replace('"', "&quot;")
        options = f'{{canvasId: "scanpipe-viewer-canvas", glbUrl: "{url}"}}'
    return (
        f"<style>{_CSS}</style>"
        '<div class="scanpipe-viewer"><canvas id="scanpipe-viewer-canvas"></canvas>'
        '<div class="bar"><button id="scanpipe-view-outside" type="button">Outside</button>'
        '<button id="scanpipe-view-inside" type="button">From the scanner</button>'
        '<span id="scanpipe-viewer-status">The 3-D view needs JavaScript and WebGL.</span>'
        "</div></div>\n"
        f"{model}\n<script>{_inline_script(viewer_script())}</script>\n"
        f"<script>window.ScanpipeViewer.start({options});</script>\n"
    )


def viewer_page(title: str, glb: bytes | None = None, glb_url: str | None = None) -> str:
    """A whole HTML page holding only the viewer."""
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(title)}</title>"
            "<style>body{margin:0;font-family:system-ui,sans-serif}"
            ".scanpipe-viewer{height:100vh;border:0}</style></head><body>\n"
            + viewer_fragment(glb=glb, glb_url=glb_url) + "</body></html>\n")


def report_section(workdir: Path) -> str:
    """The report's "3-D view" section, or a note saying why there is none."""
    try:
        glb = model_glb(workdir)
    except ArtifactError as err:
        return f'<p class="note">No 3-D view: {html.escape(str(err))}</p>'
    if len(glb) > MAX_INLINE_GLB_BYTES:
        return (f'<p class="note">No 3-D view in the report: the model is '
                f"{len(glb) / 2**20:.0f} MiB (more than {MAX_INLINE_GLB_BYTES // 2**20} MiB is "
                "not inlined); run <code>scanpipe view WORKDIR</code> to see it.</p>")
    return viewer_fragment(glb=glb)


class _Handler(http.server.BaseHTTPRequestHandler):
    page: bytes = b""
    glb: bytes = b""

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0]
        if path in ("/", "/index.html"):
            self._send(self.page, "text/html; charset=utf-8")
        elif path == "/model.glb":
            self._send(self.glb, "model/gltf-binary")
        else:
            self.send_error(404)

    def _send(self, body: bytes, content_type: str) -> None:
        self.send_response(200)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: object) -> None:
        return


def make_server(workdir: Path, host: str = "127.0.0.1",
                port: int = 0) -> http.server.ThreadingHTTPServer:
    """A local HTTP server of the workdir's viewer page (``/``) and model (``/model.glb``).

    ``port`` 0 takes a free one; read it from ``server.server_address``. The model is read
    once, when the server is made.
    """
    glb = model_glb(workdir)
    handler = type("ViewerHandler", (_Handler,), {
        "page": viewer_page(f"scanpipe: {workdir.name or workdir}",
                            glb_url="model.glb").encode("utf-8"),
        "glb": glb,
    })
    try:
        return http.server.ThreadingHTTPServer((host, port), handler)
    except OSError as err:
        raise UsageError(f"--port {port}: cannot listen on {host}:{port} "
                         f"({err.strerror or err}); give a free port or 0") from None


def serve(workdir: Path, host: str = "127.0.0.1", port: int = 0, open_browser: bool = True,
          as_json: bool = False) -> None:
    """Serve the viewer until interrupted (Ctrl-C), opening a browser on it if asked; the
    address is printed first (as one JSON object with ``as_json``)."""
    server = make_server(workdir, host, port)
    address = f"http://{host}:{server.server_address[1]}/"
    if as_json:
        print(json.dumps({"url": address, "workdir": str(workdir)}), flush=True)
    else:
        print(f"scanpipe: serving the 3-D view of {workdir} at {address} (Ctrl-C to stop)",
              flush=True)
    if open_browser:
        threading.Timer(0.3, webbrowser.open, args=(address,)).start()
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
