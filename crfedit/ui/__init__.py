"""``crfedit ui``: scribble, preview and edit in a local web page (docs/ui.md).

* :mod:`.recipe` — what the page asks for, checked, and the shell lines that replay it;
* :mod:`.session` — the model, the edit stack, the selection shown and the render caches;
* :mod:`.server` — the aiohttp server: the page, its JSON API, a WebSocket for progress.

The page itself (``static/``) is plain HTML, CSS and JavaScript shipped in the package: nothing
is fetched from the network.  Only :mod:`.server` needs the ``[ui]`` extra (aiohttp).
"""
