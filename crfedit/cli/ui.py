"""``crfedit ui``: a local web page to scribble, preview and edit (docs/ui.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import CrfError
from .common import DeviceChoice, DeviceOpt, app, user_errors

LOOPBACK = ("127.0.0.1", "localhost", "::1")


@app.command("ui")
@user_errors
def ui_cmd(
    model: Annotated[Path, typer.Argument(help="Model file (.safetensors).")],
    data: Annotated[Optional[Path], typer.Option("--data", help="The category's dataset: its train and test images to pick views from.")] = None,
    edit: Annotated[Optional[list[Path]], typer.Option("--edit", help="An edit file to start the stack with (repeatable, in the order they were made).")] = None,
    port: Annotated[int, typer.Option("--port", help="Port to listen on (0: any free port).")] = 8765,
    workdir: Annotated[Path, typer.Option("--workdir", help="Folder the page saves edits and baked models into (made when first needed).")] = Path("crfedit-ui"),
    host: Annotated[str, typer.Option("--host", help="Address to bind: 127.0.0.1 is this machine only; anything else is reachable from the network.")] = "127.0.0.1",
    open_browser: Annotated[bool, typer.Option("--open", help="Open the page in the default web browser.")] = False,
    device: DeviceOpt = DeviceChoice.auto,
) -> None:
    """Serve a local web page to scribble on views, preview the 3-D selection, edit, and manage the edit stack.

    Prints the page's URL, which carries a random session token: every request needs it.
    """
    try:
        import aiohttp  # noqa: F401
    except ImportError:
        raise CrfError("crfedit ui needs the web server of the [ui] extra: pip install -e '.[ui]' in the repository (pip install 'crfedit[ui]' from an index)") from None
    if not 0 <= port <= 65535:
        raise CrfError(f"--port {port}: expected 0-65535")
    if workdir.exists() and not workdir.is_dir():
        raise CrfError(f"--workdir {workdir}: is a file, not a folder")
    import torch

    from ..ui.server import open_page_session, serve

    session, warnings = open_page_session(model, data, list(edit or []), workdir, device.value)
    for w in warnings:
        typer.echo(f"warning: {w}", err=True)
    def ready(url: str) -> None:
        if host not in LOOPBACK:  # said once it listens there: an address it could not take is the error alone
            typer.echo(f"warning: --host {host}: the page is reachable from other machines; anyone with its URL can edit and write files in {workdir}", err=True)
        threads = torch.get_num_threads()
        typer.echo(f"crfedit ui: {model} with {len(session.entries)} edit(s), work dir {workdir}, "
                   f"{threads} CPU thread{'s' * (threads > 1)} for each of the page's two compute threads")
        typer.echo(f"open {url}  (Ctrl-C stops)", err=False)
        if open_browser:
            import webbrowser

            webbrowser.open(url)

    serve(session, host, port, ready)
    typer.echo("crfedit ui: stopped")
