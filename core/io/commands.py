"""``faceretarget convert IN OUT``: convert between file formats.

Reads ``IN`` with the registered reader (``--kind`` chooses among formats sharing an
extension) and writes ``OUT`` with the writer for its extension, atomically; a path
without an extension is written as a folder (OBJ sequence or rig folder). Examples::

    faceretarget convert head.ply head.obj                 # mesh -> mesh
    faceretarget convert take.pc2 take.glb --topology head.obj --fps 24
    faceretarget convert rig_folder rig.glb                # OBJ rig folder -> morph targets
    faceretarget convert take.csv take_llf.csv --kind weights
    faceretarget convert markers.c3d markers.trc

Refuses ``IN == OUT`` and never replaces a file it read; an existing ``OUT`` needs
``--force``. Errors are :class:`~faceretarget.errors.FaceRetargetError` subclasses (the
CLI prints them on one line).
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from ..errors import OutputError
from ..hookspecs import DATA_KINDS

__all__ = ["add_convert_arguments", "run_convert", "convert"]


def add_convert_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``convert`` arguments to ``parser``."""
    parser.add_argument("input", metavar="IN", help="file or folder to read")
    parser.add_argument("output", metavar="OUT", help="file to write (no extension: a folder of OBJ files)")
    parser.add_argument("--kind", choices=DATA_KINDS, default=None, help="what to read IN as, when its extension is ambiguous")
    parser.add_argument("--force", action="store_true", help="replace OUT if it exists (never an input)")
    parser.add_argument("--topology", metavar="MESH", default=None, help="mesh giving the triangles of a point cache or .npy")
    parser.add_argument("--fps", type=float, default=None, help="frame rate for formats that do not store it")
    return parser


def _same_path(a: Path, b: Path) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def convert(src, dst, *, kind: str | None = None, force: bool = False, **options) -> Path:
    """Read ``src`` and write it to ``dst`` (see the module docstring)."""
    from . import load, save

    src, dst = Path(src), Path(dst)
    if _same_path(src, dst):
        raise OutputError(f"{dst}: input and output are the same file; choose another output path")
    obj = load(src, kind=kind, **{k: v for k, v in options.items() if v is not None})
    return save(obj, dst, force=force, inputs=[src])


def run_convert(args: argparse.Namespace) -> int:
    """Run ``faceretarget convert`` from parsed arguments; returns the exit code (0)."""
    out = convert(args.input, args.output, kind=args.kind, force=args.force, topology=args.topology, fps=args.fps)
    print(f"wrote {out}")
    return 0
