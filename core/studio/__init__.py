"""The studio: a local web app to look at, compare, edit and export retargeted animation.

``faceretarget studio CASE`` (or ``--source ... --target ...``) serves a page on
127.0.0.1 with a random token in its URL: the performance and the retargeted character
side by side (three.js, shipped in ``static/vendor/``), a timeline, the weight curves, a
switch over every method that applies, a parameter panel generated from the manifest, an
error heat map when the answer is known, edits propagated by the method's own ``edit()``
with undo and redo, and exports (GLB, weight CSV, PC2). ``--live PORT`` retargets a Live
Link Face stream frame by frame through a streaming method.

Modules, each readable on its own:

- :mod:`.session`: the state (inputs, methods, cached results, history, export); no HTTP.
- :mod:`.app`: the Starlette routes and the security checks in front of them.
- :mod:`.server`: uvicorn on a socket bound to 127.0.0.1, the token, the URL.
- :mod:`.live`: the Live Link Face packet decoder and the streaming loop.
- :mod:`.command`: the ``faceretarget studio`` options.
- ``static/``: ``index.html``, ``app.js``, ``studio.css`` and the vendored three.js.

See docs/studio.md for the API routes, the security model and the packet format.
"""

from __future__ import annotations

__all__ = ["Session", "StudioServer"]


def __getattr__(name: str) -> type:  # the web server is imported only when it is used
    if name == "Session":
        from .session import Session

        return Session
    if name == "StudioServer":
        from .server import StudioServer

        return StudioServer
    raise AttributeError(f"module 'faceretarget.studio' has no attribute {name!r}")
