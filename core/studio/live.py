"""Live: Live Link Face packets over UDP, retargeted frame by frame by a streaming method.

The packet (Epic's Live Link Face iPhone app, ARKit mode, packet version 6; what Unreal's
``AppleARKitFaceSupport`` plugin reads in ``AppleARKitLiveLinkSource.cpp``), all numbers
big-endian (network order)::

    uint8    version                  6
    int32    n, then n bytes          device id (UTF-8)
    int32    m, then m bytes          subject name (UTF-8)
    int32    frame number             \\
    float32  sub-frame                 | the frame time (FQualifiedFrameTime)
    int32    rate numerator            |
    int32    rate denominator         /
    uint8    count                    61
    count x float32                   the values, in the order of
                                      :data:`faceretarget.naming.LIVE_LINK_NAMES`: 52 ARKit
                                      blendshape weights, then head yaw, pitch, roll and
                                      both eyes' yaw, pitch, roll

:func:`decode` reads one (an :class:`~faceretarget.errors.InputError` says what is wrong
with a bad one), :func:`encode` writes one (the simulated sender of the tests and
:func:`send`). :class:`LiveLink` receives them on ``127.0.0.1:PORT``, turns each into a
frame of the actor (the source's own blendshape rig driven by the weights, names paired by
:func:`faceretarget.naming.map_names`, turned by the head rotation, read as radians), feeds
the frames to a method's ``stream()`` and keeps the newest retargeted frame for the page,
printing the latency of every frame (packet received to retargeted vertices ready). When
frames arrive faster than they are retargeted, the older ones are dropped (counted).
"""

from __future__ import annotations

import math
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from ..errors import CapabilityError, InputError

if TYPE_CHECKING:
    from ..model import Source, TargetRig

__all__ = ["PACKET_VERSION", "N_VALUES", "Packet", "decode", "encode", "send", "LiveLink"]

PACKET_VERSION = 6
#: 52 blendshapes + head (3) + eyes (6)
N_VALUES = 61
N_SHAPES = 52
#: A packet is at most this long (two strings of up to 256 bytes and 61 values).
MAX_PACKET = 1024
_MAX_TEXT = 256


@dataclass(frozen=True)
class Packet:
    """One decoded Live Link Face packet."""

    version: int
    device_id: str
    subject: str
    frame: int
    subframe: float
    rate: tuple[int, int]
    values: np.ndarray  # (61,) float64: weights, then head and eye rotations

    @property
    def weights(self) -> np.ndarray:
        return self.values[:N_SHAPES]

    @property
    def head(self) -> np.ndarray:
        """(yaw, pitch, roll)"""
        return self.values[N_SHAPES : N_SHAPES + 3]


def decode(data: bytes) -> Packet:
    """One packet (see the module docstring); :class:`InputError` naming what is wrong."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise InputError(f"live: a packet is bytes, got {type(data).__name__}")
    data = bytes(data)
    if len(data) > MAX_PACKET:
        raise InputError(
            f"live: packet of {len(data)} bytes; Live Link Face packets are under {MAX_PACKET}"
        )
    at = 0

    def take(n: int, what: str) -> bytes:
        nonlocal at
        if at + n > len(data):
            raise InputError(
                f"live: packet of {len(data)} bytes ends inside the {what} (byte {at}); not a Live Link Face packet"
            )
        at += n
        return data[at - n : at]

    def text(what: str) -> str:
        (n,) = struct.unpack(">i", take(4, f"{what} length"))
        if not 0 <= n <= _MAX_TEXT:
            raise InputError(f"live: {what} length {n} is out of range (0..{_MAX_TEXT})")
        try:
            return take(n, what).decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(f"live: the {what} is not UTF-8") from None

    (version,) = struct.unpack(">B", take(1, "version"))
    if version != PACKET_VERSION:
        raise InputError(
            f"live: packet version {version}; this studio reads Live Link Face's ARKit packets, version {PACKET_VERSION}"
        )
    device, subject = text("device id"), text("subject name")
    frame, subframe, num, den = struct.unpack(">ifii", take(16, "frame time"))
    (count,) = struct.unpack(">B", take(1, "value count"))
    if count > N_VALUES:
        raise InputError(f"live: {count} values; a Live Link Face packet has at most {N_VALUES}")
    values = np.zeros(N_VALUES)
    values[:count] = struct.unpack(f">{count}f", take(4 * count, "values"))
    if not np.isfinite(values).all():
        raise InputError("live: the packet holds NaN or infinite values")
    return Packet(version, device, subject, frame, subframe, (num, den), values)


def encode(
    values: npt.ArrayLike,
    *,
    frame: int = 0,
    subframe: float = 0.0,
    rate: tuple[int, int] = (60, 1),
    subject: str = "faceretarget",
    device_id: str = "00000000-0000-0000-0000-000000000000",
) -> bytes:
    """A packet holding ``values`` (up to 61, in :data:`~faceretarget.naming.LIVE_LINK_NAMES` order)."""
    vals = np.asarray(values, dtype=np.float64).ravel()
    if len(vals) > N_VALUES:
        raise InputError(f"live: at most {N_VALUES} values, got {len(vals)}")
    dev, sub = device_id.encode(), subject.encode()
    return (
        struct.pack(">Bi", PACKET_VERSION, len(dev))
        + dev
        + struct.pack(">i", len(sub))
        + sub
        + struct.pack(">ifiiB", frame, subframe, rate[0], rate[1], len(vals))
        + struct.pack(f">{len(vals)}f", *vals)
    )


def send(
    port: int, frames: Iterable[npt.ArrayLike], *, fps: float = 60.0, host: str = "127.0.0.1"
) -> int:
    """Send ``frames`` ((F, <=61) values) as Live Link Face packets to ``host:port`` at
    ``fps`` (a simulated iPhone); returns the number sent."""
    sent = 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        start = time.perf_counter()
        for i, values in enumerate(frames):
            delay = start + i / fps - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            sock.sendto(encode(values, frame=i), (host, port))
            sent += 1
    return sent


def _rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    cy, sy, cp, sp, cr, sr = (f(a) for a in (yaw, pitch, roll) for f in (math.cos, math.sin))
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return ry @ rx @ rz


class Actor:
    """Live Link Face values -> one frame of the source: its own rig driven by the weights."""

    def __init__(self, source: Source) -> None:
        from ..model import MeshSequence
        from ..naming import LIVE_LINK_NAMES, map_names

        rig, perf = source.rig, source.performance
        if rig is None:
            raise CapabilityError(
                "live: the source has no blendshape rig of its own to play the Live Link Face weights on; "
                "give --source-rig (or use an evaluation case)"
            )
        if (
            source.kind != "mesh"
            or not isinstance(perf, MeshSequence)  # as kind says (for the type checker)
            or rig.neutral.n_vertices != perf.n_vertices
        ):
            raise CapabilityError(
                "live: the stream is played on the source's rig, which must have the vertices of the "
                "source mesh sequence (a mesh source and its own rig, e.g. an evaluation case)"
            )
        mapping = map_names(LIVE_LINK_NAMES[:N_SHAPES], rig.names)
        if not mapping.pairs:
            raise CapabilityError(
                f"live: none of the source rig's shapes ({', '.join(rig.names[:5])}, ...) is an ARKit / Live Link Face name"
            )
        self.matrix = mapping.matrix().T  # (52, M): w_rig = w_live @ matrix
        self.rig = rig
        self.centre = rig.neutral.vertices.mean(axis=0)

    def frame(self, values: np.ndarray) -> np.ndarray:
        local = self.rig.evaluate((values[:N_SHAPES] @ self.matrix)[None])[0]
        rot = _rotation(*values[N_SHAPES : N_SHAPES + 3])
        return (local - self.centre) @ rot.T + self.centre


def streaming_method(source: Source, target: TargetRig, name: str | None = None) -> str:
    """The streaming method to use: ``name`` (checked), else the first that applies."""
    from ..registry import registry

    reg = registry()
    if name is not None:
        entry = reg.resolve(name)
        if not entry.capabilities.stream:
            raise CapabilityError(
                f"live: {entry.name} does not stream (its manifest: stream = false)"
            )
        why = entry.cls.why_not(source, target)
        if why:
            raise CapabilityError(f"live: {why}")
        return entry.name
    streaming = [e for _, e in sorted(reg.retargeters.items()) if e.capabilities.stream]
    for entry in streaming:
        if entry.cls.why_not(source, target) is None:
            return entry.name
    names = ", ".join(e.name for e in streaming) or "none is registered"
    raise CapabilityError(
        f"live: no streaming method applies to these inputs (streaming methods: {names})"
    )


class LiveLink:
    """Receive Live Link Face packets on ``127.0.0.1:port`` and retarget them frame by frame.

    :meth:`start` binds the port (0: any free one, see :attr:`port`) and starts a thread that
    fits the streaming method on (source, target) and then serves the stream; :meth:`latest`
    gives the newest frame to the page; :meth:`stop` ends it.
    """

    def __init__(
        self,
        source: Source,
        target: TargetRig,
        port: int,
        *,
        method: str | None = None,
        params: dict | None = None,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.source, self.target = source, target
        self.method = streaming_method(source, target, method)
        self.params = dict(params or {})
        self.actor = Actor(source)
        self.requested_port = port
        self.port = port
        self.status = "starting"
        self.error = ""
        self.frames = self.dropped = self.bad_packets = 0
        self.latency_ms: list[float] = []
        self._log = log or (lambda line: print(line, file=sys.stdout, flush=True))
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cond = threading.Condition()
        self._latest: dict[str, Any] | None = None
        self._pending: tuple[float, Any] | None = None

    def start(self) -> LiveLink:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind(("127.0.0.1", self.requested_port))
        except OSError as exc:
            sock.close()
            raise InputError(
                f"live: cannot listen on UDP 127.0.0.1:{self.requested_port} ({exc.strerror}); choose another --live port"
            ) from None
        sock.settimeout(0.2)
        self._sock, self.port = sock, sock.getsockname()[1]
        self._thread = threading.Thread(target=self._run, name="studio-live", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        if self._sock is not None:
            self._sock.close()

    def info(self) -> dict[str, Any]:
        lat = self.latency_ms[-200:]
        return {
            "port": self.port,
            "method": self.method,
            "status": self.status,
            "error": self.error,
            "frames": self.frames,
            "dropped": self.dropped,
            "bad_packets": self.bad_packets,
            "latency_ms": {
                "last": lat[-1] if lat else None,
                "median": float(np.median(lat)) if lat else None,
                "max": max(lat) if lat else None,
            },
        }

    def latest(self, after: int = 0, timeout: float = 1.0) -> dict[str, Any] | None:
        """The newest retargeted frame if its number is above ``after`` (waiting up to
        ``timeout`` seconds for one): ``seq``, ``source`` (P, 3), ``target`` (V, 3), ``latency_ms``."""
        with self._cond:
            self._cond.wait_for(
                lambda: self._latest is not None and self._latest["seq"] > after, timeout=timeout
            )
            if self._latest is None or self._latest["seq"] <= after:
                return None
            return self._latest

    # -- the thread ------------------------------------------------------------------------------
    def _run(self) -> None:
        from .. import get

        try:
            self.status = "fitting"
            self._log(f"live: fitting {self.method} for the stream ...")
            retargeter = get(self.method, **self.params).fit(self.source, self.target)
        except Exception as exc:  # shown in the page; the studio keeps running
            self.status, self.error = "failed", f"{type(exc).__name__}: {exc}"
            self._log(f"live: {self.method} could not be fitted: {self.error}")
            return
        self.status = "waiting"
        self._log(f"live: listening for Live Link Face packets on udp://127.0.0.1:{self.port}")
        while not self._stop.is_set():
            try:
                for out in retargeter.stream(self._packets()):
                    self._publish(out)
            except Exception as exc:  # one bad frame: report it and start a new stream
                self.error = f"{type(exc).__name__}: {exc}"
                self._log(f"live: frame failed ({self.error}); the stream starts again")

    def _packets(self) -> Iterator[np.ndarray]:
        sock = self._sock
        assert sock is not None
        while not self._stop.is_set():
            try:
                data, _ = sock.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            received = time.perf_counter()
            sock.setblocking(False)
            try:  # only the newest packet counts
                while True:
                    data, _ = sock.recvfrom(65536)
                    self.dropped += 1
            except (BlockingIOError, OSError):
                pass
            finally:
                sock.settimeout(0.2)
            try:
                packet = decode(data)
            except InputError as exc:
                self.bad_packets += 1
                self.error = str(exc)
                if self.bad_packets <= 3:
                    self._log(f"live: {exc} (packet ignored)")
                continue
            points = self.actor.frame(packet.values)
            self._pending = (received, points)
            yield points

    def _publish(self, out: np.ndarray) -> None:
        assert self._pending is not None
        received, points = self._pending
        latency = (time.perf_counter() - received) * 1e3
        self.frames += 1
        self.status = "streaming"
        self.latency_ms.append(latency)
        del self.latency_ms[:-1000]
        with self._cond:
            self._latest = {
                "seq": self.frames,
                "source": np.asarray(points, dtype=np.float32),
                "target": np.asarray(out, dtype=np.float32),
                "latency_ms": latency,
            }
            self._cond.notify_all()
        self._log(
            f"live frame {self.frames}: {latency:.1f} ms (packet received to retargeted frame)"
        )
