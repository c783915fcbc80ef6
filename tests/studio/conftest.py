"""Fixtures of the studio tests: the small case, a registry with a method that fails, studio
servers on 127.0.0.1 in threads (helpers in ``studio_helpers.py``)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from studio_helpers import CASE, BoomPlugin  # noqa: E402


@pytest.fixture(scope="module")
def boom_registry():
    """The built-ins and ``studio_boom``, as the process-wide registry for one test module."""
    from faceretarget import registry as registry_module

    old = registry_module._REGISTRY
    registry_module._REGISTRY = registry_module.Registry().load(
        extra=[("studio_boom", BoomPlugin())]
    )
    yield registry_module._REGISTRY
    registry_module._REGISTRY = old


@pytest.fixture(scope="module")
def case():
    from faceretarget.evaluation.harness import resolve_case

    return resolve_case(CASE)


@pytest.fixture(scope="module")
def start_studio(tmp_path_factory):
    """``start_studio(case, files=(), live=None) -> StudioServer`` serving in a thread; all
    stopped at the end of the module."""
    from faceretarget.studio.server import StudioServer
    from faceretarget.studio.session import Session

    servers = []

    def start(case, files=(), live=None, out=None):
        session = Session(
            case.source,
            case.target,
            truth=case.truth,
            name=case.name,
            files=files,
            out_dir=out or tmp_path_factory.mktemp("exports"),
            face_height=case.meta.get("face_height"),
        )
        if live is not None:
            from faceretarget.studio.live import LiveLink

            session.live = LiveLink(case.source, case.target, 0, log=live.append).start()
        server = StudioServer(session).start()
        servers.append(server)
        return server

    yield start
    for server in servers:
        server.stop()
