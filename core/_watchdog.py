"""The process watchdog of :mod:`faceretarget._deadline` (a script: standard library only).

    python -I _watchdog.py TARGET_PID

Reads commands from its standard input, one a line: ``arm SECONDS HEXMESSAGE`` (kill the
target in SECONDS unless disarmed first) and ``disarm``. When an armed deadline passes it
writes the message to its standard error (the target's, inherited) and SIGKILLs the
target. End of input (the target closed the pipe, or exited) ends it. It runs in a process
of its own, so nothing in the target (a plugin that ignores or blocks every signal, or
compiled code that never releases the GIL) can keep it from firing.
"""

from __future__ import annotations

import os
import select
import signal
import sys
import time


def main(target: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the target's to handle
    deadline: float | None = None
    message = b""
    pending = b""
    while True:
        wait = None if deadline is None else max(0.0, deadline - time.monotonic())
        ready, _, _ = select.select([0], [], [], wait)
        if not ready:
            if deadline is not None and time.monotonic() >= deadline:
                try:
                    os.write(2, message)
                finally:
                    try:
                        os.kill(target, signal.SIGKILL)
                    except OSError:
                        pass
                os._exit(0)
            continue
        chunk = os.read(0, 65536)
        if not chunk:
            os._exit(0)
        pending += chunk
        while b"\n" in pending:
            line, pending = pending.split(b"\n", 1)
            if line.startswith(b"arm "):
                _, seconds, text = line.split(b" ", 2)
                deadline, message = (
                    time.monotonic() + float(seconds),
                    bytes.fromhex(text.decode("ascii")),
                )
            elif line == b"disarm":
                deadline = None


if __name__ == "__main__":
    main(int(sys.argv[1]))
