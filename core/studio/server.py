"""Serving the studio: a uvicorn server on a socket bound to 127.0.0.1, with a fresh token.

server = StudioServer(session)          # binds 127.0.0.1 (port 0: any free one)
print(server.url)                       # http://127.0.0.1:PORT/?token=...
server.serve()                          # until Ctrl-C; or start() / stop() in a thread
"""

from __future__ import annotations

import secrets
import socket
import threading
import time
from typing import TYPE_CHECKING, Any

from ..errors import FaceRetargetError, InputError
from .session import Session

if TYPE_CHECKING:
    import uvicorn

__all__ = ["StudioServer"]


class StudioServer:
    """The studio's HTTP server for ``session``; nothing listens until :meth:`serve` or
    :meth:`start`, but the port is bound at once (so :attr:`url` is known)."""

    def __init__(self, session: Session, *, port: int = 0, token: str | None = None) -> None:
        from .app import create_app

        self.session = session
        self.token = token or secrets.token_urlsafe(32)
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
        except OSError as exc:
            sock.close()
            raise InputError(
                f"studio: cannot listen on 127.0.0.1:{port} ({exc.strerror}); choose another --port (0: any free one)"
            ) from None
        sock.listen(128)  # connections wait in the queue until the server accepts them
        self.socket = sock
        self.port = sock.getsockname()[1]
        self.app = create_app(session, token=self.token, port=self.port)
        self._server: Any = None
        self._thread: threading.Thread | None = None

    @property
    def origin(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def url(self) -> str:
        return f"{self.origin}/?token={self.token}"

    def _uvicorn(self) -> uvicorn.Server:
        import uvicorn

        config = uvicorn.Config(
            self.app,
            log_level="warning",
            access_log=False,
            lifespan="off",
            timeout_graceful_shutdown=2,
        )
        self._server = uvicorn.Server(config)
        return self._server

    def serve(self) -> None:
        """Serve in this thread until interrupted (Ctrl-C)."""
        try:
            self._uvicorn().run(sockets=[self.socket])
        finally:
            self.close()

    def start(self) -> StudioServer:
        """Serve in a background thread (tests, benchmarks); returns when it answers."""
        server = self._uvicorn()
        self._thread = threading.Thread(
            target=server.run, kwargs={"sockets": [self.socket]}, name="studio", daemon=True
        )
        self._thread.start()
        deadline = time.monotonic() + 30
        while not server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise FaceRetargetError("studio: the server did not start (see the log above)")
            time.sleep(0.01)
        return self

    def stop(self) -> None:
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=10)
        self.close()

    def close(self) -> None:
        if self.session.live is not None:
            self.session.live.stop()
        self.socket.close()
