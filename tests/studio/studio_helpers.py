"""Helpers of the studio tests: the small case, a method that fails, raw HTTP requests (any
Host / Origin / token) and PNG pixels."""

from __future__ import annotations

import http.client
import json
import struct
import zlib
from typing import ClassVar

import faceretarget as fr
from faceretarget import hookimpl
from faceretarget.errors import NumericalError
from faceretarget.validation import Options

#: small enough for every method to fit in well under a second (numba kernels compiled)
CASE = "synthetic-human?resolution=600&n_frames=60"


class BoomRetargeter(fr.Retargeter):
    """A method that fails in fit: ``fail="crash"`` an unexpected RuntimeError, ``"numerical"``
    a NumericalError (a method failing on its inputs)."""

    name: ClassVar[str] = "studio_boom"
    capabilities: ClassVar[fr.Capabilities] = fr.Capabilities(sources=("markers", "mesh"))
    parameter_constraints: ClassVar[dict] = {"fail": [Options(["crash", "numerical"])]}
    parameter_docs: ClassVar[dict] = {"fail": "how to fail"}

    def __init__(self, *, fail: str = "crash"):
        self.fail = fail

    def _fit(self, source, target):
        if self.fail == "numerical":
            raise NumericalError("studio_boom: the system is singular (on purpose)")
        raise RuntimeError("kaboom (on purpose)")

    def _retarget(self, source):  # pragma: no cover - never fitted
        raise AssertionError


class BoomPlugin:
    @hookimpl
    def faceretarget_retargeters(self):
        return [BoomRetargeter]


class Answer:
    def __init__(self, status: int, headers: dict, body: bytes):
        self.status, self.headers, self.body = status, headers, body

    def json(self):
        return json.loads(self.body)

    def __repr__(self) -> str:
        return f"<{self.status} {self.body[:200]!r}>"


def call(
    server,
    path: str,
    *,
    method: str = "GET",
    body=None,
    token: str | None = "header",
    host: str | None = None,
    origin: str | None = None,
    raw: bytes | None = None,
) -> Answer:
    """One HTTP request to ``server`` with full control of Host, Origin and the token:
    ``token="header"`` (the right one in X-Studio-Token), ``"query"`` (in ?token=), None, or
    any other string (sent as the header)."""
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=60)
    if token == "query":
        path += ("&" if "?" in path else "?") + f"token={server.token}"
    conn.putrequest(method, path, skip_host=True)
    conn.putheader("Host", host or f"127.0.0.1:{server.port}")
    if origin:
        conn.putheader("Origin", origin)
    if token == "header":
        conn.putheader("X-Studio-Token", server.token)
    elif token not in (None, "query"):
        conn.putheader("X-Studio-Token", token)
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    if data is not None:
        conn.putheader("Content-Type", "application/json")
        conn.putheader("Content-Length", str(len(data)))
    conn.endheaders(data)
    res = conn.getresponse()
    answer = Answer(res.status, {k.lower(): v for k, v in res.getheaders()}, res.read())
    conn.close()
    return answer


def png_pixels(data: bytes) -> tuple[int, int, list[bytes], int]:
    """(width, height, unfiltered rows, bytes per pixel) of an 8-bit RGB/RGBA PNG."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, width = 8, b"", 0
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        kind, chunk = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        if kind == b"IHDR":
            width, height, depth, color = struct.unpack(">IIBB", chunk[:10])
            assert depth == 8 and color in (2, 6)
            bpp = 3 if color == 2 else 4
        elif kind == b"IDAT":
            idat += chunk
        pos += 12 + n
    raw, stride, rows, prev = zlib.decompress(idat), width * bpp, [], bytearray(width * bpp)
    for y in range(height):
        f, line = (
            raw[y * (stride + 1)],
            bytearray(raw[y * (stride + 1) + 1 : (y + 1) * (stride + 1)]),
        )
        for i in range(stride):
            a = line[i - bpp] if i >= bpp else 0
            b, c = prev[i], prev[i - bpp] if i >= bpp else 0
            if f == 1:
                line[i] = (line[i] + a) & 255
            elif f == 2:
                line[i] = (line[i] + b) & 255
            elif f == 3:
                line[i] = (line[i] + (a + b) // 2) & 255
            elif f == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append(bytes(line))
        prev = line
    return width, height, rows, bpp


def colours(png: bytes, step: int = 3) -> list[tuple[int, int, int]]:
    """Every ``step``-th pixel's (r, g, b) of a PNG."""
    width, height, rows, bpp = png_pixels(png)
    return [
        tuple(row[x * bpp : x * bpp + 3]) for row in rows[::step] for x in range(0, width, step)
    ]
