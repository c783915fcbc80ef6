"""``faceretarget studio``: its options, and starting the server.

Imported when the command line is built, so it imports nothing heavy: the web server
(Starlette, uvicorn) is imported only when the command runs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import InputError

if TYPE_CHECKING:
    from ..model import Animation, Source, TargetRig

__all__ = ["add_studio_arguments", "run_studio"]


def add_studio_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    from ..cli import add_source_target_arguments

    parser.add_argument(
        "case",
        nargs="?",
        metavar="CASE",
        help="a built-in evaluation case (synthetic-human, synthetic-stylized, ict, cross_rig, cross_topology; "
        "keywords after ?, e.g. 'synthetic-human?n_frames=300') or a case bundle .npz; or give --source and --target",
    )
    add_source_target_arguments(parser, required=False)
    studio = parser.add_argument_group("studio")
    studio.add_argument("--method", help="the method shown first (default: the first that edits)")
    studio.add_argument(
        "--set",
        dest="params",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a parameter of --method (repeatable)",
    )
    studio.add_argument(
        "--port",
        type=int,
        default=0,
        help="TCP port on 127.0.0.1 (default 0: any free port; the URL says which)",
    )
    studio.add_argument(
        "--out",
        metavar="DIR",
        default=".",
        help="folder the exports are written into (default: the current folder); never over an existing file",
    )
    studio.add_argument(
        "--live",
        type=int,
        metavar="PORT",
        help="receive a Live Link Face stream on UDP 127.0.0.1:PORT (0: any free port) and retarget it frame by frame",
    )
    studio.add_argument(
        "--live-method",
        metavar="NAME",
        help="the streaming method for --live (default: the first streaming method that applies)",
    )
    studio.add_argument(
        "--open", action="store_true", help="open the page in the default web browser"
    )
    return parser


def load_inputs(
    args: argparse.Namespace,
) -> tuple[Source, TargetRig, Animation | None, str, list[str]]:
    """``(source, target, truth, name, files)`` from CASE or --source/--target."""
    from ..cli import _run_inputs, load_run_source, load_run_target

    given = _run_inputs(args)
    if args.case and given:
        raise InputError(
            "studio: give either a CASE or --source/--target (and their parts), not both"
        )
    if args.case:
        path = Path(args.case)
        if path.suffix.lower() == ".npz" and path.is_file():
            from ..io.sources import is_case, load_bundle

            case = load_bundle(path)
            if not is_case(case):
                raise InputError(
                    f"studio: {path} holds a {type(case).__name__}, not a case; give it as --source or --target"
                )
            files = [str(path)]
        else:
            from ..evaluation.harness import resolve_case

            case = resolve_case(args.case)
            files = []
        name = getattr(case, "name", "") or path.stem
        return case.source, case.target, getattr(case, "truth", None), name, files
    if not (args.source and args.target):
        raise InputError(
            "studio: give a CASE (e.g. `faceretarget studio synthetic-human`) or both --source and --target"
        )
    source, target = load_run_source(args), load_run_target(args)
    return source, target, None, Path(args.source).stem, given


def run_studio(args: argparse.Namespace) -> int:
    from .._args import parse_sets
    from .server import StudioServer
    from .session import Session

    if args.params and not args.method:
        raise InputError("studio: --set needs --method (the method the parameters belong to)")
    source, target, truth, name, files = load_inputs(args)
    session = Session(source, target, truth=truth, name=name, files=files, out_dir=args.out)
    if args.method:
        method = session.method(args.method)["name"]
        session.defaults = {
            "method": method,
            "params": session.check_params(method, parse_sets(args.params)),
        }
    if args.live is not None:
        from .live import LiveLink

        session.live = LiveLink(source, target, args.live, method=args.live_method).start()
    server = StudioServer(session, port=args.port)
    print(f"faceretarget studio: {server.url}", flush=True)
    print(
        f"  {name}: {source.n_frames} frames; exports go to {Path(args.out).resolve()}; "
        + (f"live on udp://127.0.0.1:{session.live.port}; " if session.live else "")
        + "Ctrl-C stops",
        flush=True,
    )
    if args.open:
        import webbrowser

        webbrowser.open(server.url)
    try:
        server.serve()
    except KeyboardInterrupt:
        pass
    print("faceretarget studio: stopped", file=sys.stderr)
    return 0
