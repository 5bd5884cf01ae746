"""``scanpipe view``: the interactive 3-D view of a workdir's model, served locally."""

from __future__ import annotations

from pathlib import Path

import typer

from scanpipe.cli.common import JSON


def view(
    workdir: Path = typer.Argument(..., help="A workdir or folder of artifacts with a mesh."),
    port: int = typer.Option(0, "--port", min=0, max=65535,
                             help="The local port (0: a free one, printed)."),
    host: str = typer.Option("127.0.0.1", "--host",
                             help="The address to listen on (default: this machine only)."),
    browser: bool = typer.Option(True, "--browser/--no-browser",
                                 help="Open the page in the default browser."),
    as_json: bool = JSON,
) -> None:
    """Serve the textured model in an interactive 3-D view (offline: three.js is bundled)."""
    from scanpipe.viewer import serve

    serve(workdir, host=host, port=port, open_browser=browser, as_json=as_json)


def register(app: typer.Typer) -> None:
    """Add ``view`` to the main app."""
    app.command("view")(view)
