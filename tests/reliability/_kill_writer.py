"""Child process of test_no_data_loss: start a registered writer and stop in the middle of it.

    python _kill_writer.py WRITER_NAME OUT MODE builtin|plugin

MODE ``mid``: every file opened for writing under OUT's folder writes half of its first
chunk, flushes, prints ``MID`` and sleeps (the parent SIGKILLs it there).
MODE ``commit``: ``os.replace`` prints ``COMMIT`` and sleeps (the data is complete, the
rename has not happened). Prints ``DONE`` if the writer finished without being stopped.
"""

import builtins
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from reliability import samples  # noqa: E402


def find_writer(name: str, builtin: bool):
    """The writer called ``name`` (built-ins without loading every plugin: faster)."""
    if builtin:
        from faceretarget.io.builtin import builtin_writers

        return next(w for w in builtin_writers() if w.name == name)
    from faceretarget.registry import registry

    return next(w for w, _ in registry().writers if w.name == name)


def stop(tag: str) -> None:
    print(tag, flush=True)
    time.sleep(600)


class HalfWriter:
    """A file object that writes half of its first chunk, then stops the process."""

    def __init__(self, fh):
        self._fh = fh

    def write(self, data):
        half = max(1, len(data) // 2)
        self._fh.write(data[:half])
        self._fh.flush()
        os.fsync(self._fh.fileno())
        stop("MID")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return self._fh.__exit__(*exc)

    def __iter__(self):
        return iter(self._fh)

    def __getattr__(self, name):
        return getattr(self._fh, name)


def main() -> None:
    name, out, mode, builtin = sys.argv[1:5]
    writer = find_writer(name, builtin == "builtin")
    obj = samples.sample(writer.kind, frames=12, n=6)
    folder = os.path.dirname(os.path.abspath(out))
    if mode == "mid":
        real_open = builtins.open

        def open_(file, mode="r", *args, **kwargs):
            fh = real_open(file, mode, *args, **kwargs)
            if (
                isinstance(file, (str, os.PathLike))
                and any(c in mode for c in "wxa+")
                and os.path.abspath(os.fspath(file)).startswith(folder)
            ):
                return HalfWriter(fh)
            return fh

        builtins.open = open_
    else:
        real_replace = os.replace

        def replace(src, dst, *args, **kwargs):
            if os.path.abspath(os.fspath(dst)) == os.path.abspath(out):
                stop("COMMIT")
            return real_replace(src, dst, *args, **kwargs)

        os.replace = replace
    writer.write(obj, out, force=True)
    print("DONE", flush=True)


if __name__ == "__main__":
    main()
