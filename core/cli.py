"""The ``faceretarget`` command.

    faceretarget list                       registered retargeters (and plugins that failed)
    faceretarget info NAME                  parameters with defaults and meaning
    faceretarget run NAME --source S --target T --out O [--set k=v ...]
    faceretarget convert IN OUT             between file formats
    faceretarget formats                    readers and writers
    faceretarget compare / demo / batch     evaluation harness (see docs/evaluation.md)
    faceretarget studio [CASE]              local web app: view, edit, export, live (docs/studio.md)

Errors are printed as one line on stderr with a non-zero exit status; ``--debug``
shows the traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from importlib import import_module
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from ._args import parse_sets
from ._json import jsonable
from ._version import __version__
from .errors import (
    CapabilityError,
    FaceRetargetError,
    FileFormatError,
    InputError,
    PluginError,
    PluginOutputError,
)
from .hookspecs import DATA_KINDS

if TYPE_CHECKING:
    import numpy as np

    from .model import LayeredRig, Source, TargetRig
    from .registry import PluginInfo, RetargeterInfo

_T = TypeVar("_T")

EXIT_FAILED = (
    1  # the command ran to its end, but some of its runs or jobs failed (see --keep-going)
)
EXIT_ERROR = 2
EXIT_INTERNAL = 3


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 0
    code, message = _dispatch(args)
    _warn_skipped_plugins(args)
    if message:
        print(message, file=sys.stderr)
    return code


def _dispatch(args: argparse.Namespace) -> tuple[int, str]:
    """Run the sub-command: ``(exit status, error line or "")``. With ``--debug`` the
    traceback is printed too, and the exit status stays the same (2 for an error)."""
    try:
        return int(args.handler(args) or 0), ""
    except KeyboardInterrupt:
        return 130, "faceretarget: interrupted"
    except FaceRetargetError as exc:
        _traceback(args)
        return EXIT_ERROR, f"faceretarget: error: {_one_line(exc)}"
    except BrokenPipeError:
        return 0, ""
    except OSError as exc:  # the file system said no (disk full, permissions): not our bug
        _traceback(args)
        return EXIT_ERROR, f"faceretarget: error: {_one_line(exc)}"
    except Exception as exc:  # an unexpected failure: still one line unless --debug
        _traceback(args)
        return EXIT_INTERNAL, (
            f"faceretarget: internal error: {type(exc).__name__}: {_one_line(exc)}"
            + ("" if args.debug else " (run with --debug for the traceback)")
        )
    except BaseException as exc:  # SystemExit (or another BaseException) from code run in this process: never a success
        _traceback(args)
        return EXIT_ERROR, (
            f"faceretarget: error: the command was ended by {type(exc).__name__}({_exit_arg(exc)}) raised in "
            f"{_origin(exc)} before it finished; nothing more was done"
            + ("" if args.debug else " (run with --debug for the traceback)")
        )


def _traceback(args: argparse.Namespace) -> None:
    """With ``--debug``: the traceback of the exception being handled, on stderr."""
    if getattr(args, "debug", False):
        import traceback

        traceback.print_exc(file=sys.stderr)


def _exit_arg(exc: BaseException) -> str:
    return ", ".join(repr(a) for a in exc.args)


def _origin(exc: BaseException) -> str:
    """``file:line`` of the innermost frame of ``exc``'s traceback (where it was raised)."""
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    if tb is None:
        return "an unknown place"
    return f"{tb.tb_frame.f_code.co_filename}:{tb.tb_lineno}"


def _warn_skipped_plugins(args: argparse.Namespace) -> None:
    """One warning line per third-party plugin that failed to load and was skipped (``list``
    shows them in its own output), if this command loaded the plugins at all."""
    if getattr(args, "command", None) == "list":
        return
    module = sys.modules.get("faceretarget.registry")
    loaded = getattr(module, "_REGISTRY", None) if module is not None else None
    for info in getattr(loaded, "failures", None) or []:
        print(
            f"faceretarget: warning: plugin {info.name!r} ({info.origin}) was skipped: {_one_line(Exception(info.error or ''))}",
            file=sys.stderr,
        )


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return " ".join(text.split())


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="faceretarget", description="Facial animation retargeting."
    )
    parser.add_argument("--version", action="version", version=f"faceretarget {__version__}")
    parser.add_argument(
        "--debug",
        action="store_true",
        help="show the traceback of an error (the exit status stays the same)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser(
        "list",
        help="list registered retargeters",
        description="List every registered retargeter (built-in and from installed plugins) with the sources it takes, "
        "its output, whether it edits and streams, and its origin; then the plugins that failed to load.",
    )
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(handler=cmd_list)

    p = sub.add_parser(
        "info",
        help="describe one retargeter: paper, capabilities, parameters",
        description="Describe one retargeter: its paper, the sources it takes and what it needs (landmarks, feature "
        "lines, examples, layers: the `run` options that give them), and every parameter with its default and meaning.",
        epilog="example: faceretarget info NAME (a name or alias from faceretarget list)",
    )
    p.add_argument("name", help="retargeter name or alias (see `faceretarget list`)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(handler=cmd_info)

    p = sub.add_parser(
        "run",
        help="retarget a performance file onto a target rig file",
        description="Retarget a performance (--source) onto a character (--target) with one method and write the "
        "result (--out). Every part a method needs can come from ordinary files: landmarks, feature lines, example "
        "poses and layered poses for either side (see `faceretarget info NAME` for what a method needs, and "
        "`faceretarget cases export NAME DIR` for a complete set of files to try). A faceretarget bundle (.npz "
        "holding a source, target or whole case) can stand for --source or --target; the options below replace "
        "its parts.",
        epilog="example: faceretarget run NAME --source shot.c3d --target hero.glb --landmarks hero_landmarks.json --out shot_hero.glb",
    )
    p.add_argument("name", help="retargeter name or alias (see `faceretarget list`)")
    add_source_target_arguments(p)
    out = p.add_argument_group("output")
    out.add_argument(
        "--out",
        required=True,
        help="output file (.glb, .npz, .pc2, .csv, or a folder for an OBJ sequence)",
    )
    out.add_argument(
        "--set",
        dest="params",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="retargeter parameter (repeatable), e.g. --set alpha=0.02",
    )
    out.add_argument(
        "--force", action="store_true", help="overwrite an existing output (never an input)"
    )
    p.set_defaults(handler=cmd_run)

    p = sub.add_parser(
        "formats",
        help="list file formats that can be read and written",
        description="List every registered reader and writer: name, what it reads or writes, file extensions; "
        "for a plugin's format, its origin and priority, and where two share an extension and kind, which one wins "
        "(the other is shadowed: a reader then gets only the files the winner declines).",
    )
    p.set_defaults(handler=cmd_formats)

    p = sub.add_parser(
        "demo",
        help="run every method on built-in cases and write a report (the main job)",
        description="Build the synthetic human and stylized cases and the ICT-FaceKit case, run every registered method "
        "and the paper reproductions, and write report.html, results.csv/json and a GLB per (case, method) into a new folder.",
    )
    _attach(p, "faceretarget.evaluation.commands", "demo")
    p = sub.add_parser(
        "compare",
        help="compare retargeters on evaluation cases",
        description="Run retargeters on built-in cases with a known answer, print the ranking, and optionally write the "
        "report and tables (see docs/evaluation.md).",
        epilog="example: faceretarget compare --cases synthetic ict --methods NAME NAME --out report/",
    )
    _attach(p, "faceretarget.evaluation.commands", "compare")
    p = sub.add_parser(
        "batch",
        help="run a manifest of (shot, character, method) jobs",
        description="Run the [[job]] entries of a TOML manifest (shot, character, method, params, out) in parallel "
        "worker processes or on Dask; jobs whose output exists are skipped, so a stopped batch resumes.",
        epilog="example manifest: `faceretarget cases export synthetic-human take/` writes take/batch.toml",
    )
    _attach(p, "faceretarget.evaluation.commands", "batch")
    p = sub.add_parser(
        "convert",
        help="convert between file formats",
        description="Read IN with the reader for its extension (--kind chooses) and write OUT with the writer for its "
        "extension, atomically; never over an input.",
        epilog="example: faceretarget convert take.pc2 take.glb --topology actor.obj",
    )
    _attach(p, "faceretarget.io.commands", "convert")
    p = sub.add_parser(
        "cases",
        help="list the built-in cases, or export one as ordinary files",
        description="The built-in evaluation cases: `cases list` names them, `cases export NAME DIR` writes one as ordinary files to try `run` and `batch` on.",
    )
    _attach(p, "faceretarget.io.commands", "cases")
    p = sub.add_parser(
        "warmup",
        help="compile every numerical kernel ahead (once per machine), so the first real run does not wait",
        description="Fit and retarget every built-in method on tiny built-in cases, which compiles and caches the numba "
        "kernels they use (the first run otherwise pauses for a few minutes while they compile); prints the time per method.",
    )
    _attach(p, "faceretarget.evaluation.commands", "warmup")
    p = sub.add_parser(
        "studio",
        help="open a local web app: view, compare, edit and export retargeted animation, or retarget a live stream",
        description="Start a local web app (127.0.0.1, a random token in its URL) showing the performance and the "
        "retargeted character side by side: switch methods, set their parameters, edit a frame and let the method "
        "propagate it, undo, export GLB / weight CSV / PC2; with --live, retarget a Live Link Face stream frame by "
        "frame. Prints the URL to open. Reads only the files named here (see docs/studio.md).",
        epilog="examples: faceretarget studio synthetic-human   |   faceretarget studio --source shot.c3d --target "
        "hero.glb --landmarks hero.json   |   faceretarget studio synthetic-human --live 11111",
    )
    _attach(p, "faceretarget.studio.command", "studio")
    return parser


def add_source_target_arguments(parser: argparse.ArgumentParser, *, required: bool = True) -> None:
    """The options that read a performance and a character from files (``run``, ``studio``):
    ``--source`` and its parts, ``--target`` and its parts (see :func:`load_run_source`)."""
    src = parser.add_argument_group("source (the performance)")
    src.add_argument(
        "--source",
        required=required,
        help="performance: markers (c3d/trc/csv), mesh sequence (folder/npz/pc2/mdd/npy), weights csv, or a source/case bundle .npz",
    )
    src.add_argument(
        "--source-kind",
        choices=DATA_KINDS,
        help="what to read --source as when its extension is ambiguous (e.g. a .glb)",
    )
    src.add_argument(
        "--topology",
        metavar="MESH",
        help="mesh giving the triangles of a point cache (.pc2/.mdd/.npy) source, same vertex order",
    )
    src.add_argument(
        "--source-neutral",
        metavar="MESH",
        help="the actor's neutral (rest) mesh of a mesh-sequence source, same vertex order (default: frame 0); also gives its triangles",
    )
    src.add_argument(
        "--fps", type=float, help="frame rate of a source format that does not store it"
    )
    src.add_argument(
        "--source-landmarks",
        metavar="FILE",
        help="landmark vertex ids on the source mesh, in the order of the target's (json/txt); markers need none",
    )
    src.add_argument(
        "--source-feature-lines",
        metavar="JSON",
        help="feature lines on the source mesh: {line name: [vertex ids]}",
    )
    src.add_argument(
        "--source-examples",
        metavar="FILE",
        help="source example poses: npz (examples (M, V, 3), example_names) or a folder of meshes",
    )
    src.add_argument(
        "--source-rig",
        metavar="FILE",
        help="the actor's own blendshape rig, needed with a weight-curve source",
    )
    src.add_argument(
        "--source-head-motion",
        metavar="NPY",
        help="(F, 4, 4) head motion of the source, when it is known",
    )
    src.add_argument(
        "--actor-layers",
        metavar="NPZ",
        help="the actor's layered poses, a faceretarget layers .npz (layers)",
    )
    tgt = parser.add_argument_group("target (the character)")
    tgt.add_argument(
        "--target",
        required=required,
        help="character: glb/gltf with morph targets, folder of OBJs, a mesh, or a target/case bundle .npz",
    )
    tgt.add_argument(
        "--target-kind",
        choices=DATA_KINDS,
        help="what to read --target as, e.g. rig for a glb that also holds an animation",
    )
    tgt.add_argument(
        "--landmarks",
        metavar="FILE",
        help="target landmark vertex ids (json/txt/file.npz:KEY), when the target file has none",
    )
    tgt.add_argument(
        "--feature-lines",
        metavar="JSON",
        help="feature lines on the target mesh: {line name: [vertex ids]}",
    )
    tgt.add_argument(
        "--examples",
        metavar="FILE",
        help="target example poses, paired with the source's by name: npz or folder of meshes",
    )
    tgt.add_argument(
        "--layers",
        metavar="NPZ",
        help="the character's layered poses and region masks, a faceretarget layers .npz (layers)",
    )


def _attach(parser: argparse.ArgumentParser, module_name: str, command: str) -> None:
    """Let ``module_name`` add its arguments and handle the sub-command."""
    try:
        module = import_module(module_name)
        getattr(module, f"add_{command}_arguments")(parser)
        run = getattr(module, f"run_{command}")
    except (ImportError, AttributeError) as exc:
        reason = f"{module_name} is not available ({exc})"

        def run(args: argparse.Namespace, _reason: str = reason) -> int:
            raise FaceRetargetError(f"`faceretarget {command}` cannot run: {_reason}")

        parser.add_argument("rest", nargs=argparse.REMAINDER)
    parser.set_defaults(handler=run)


# ---------------------------------------------------------------------------------------
def cmd_list(args: argparse.Namespace) -> int:
    from .registry import catalogue

    reg = catalogue()  # manifests only: no plugin code imported
    rows = [entry.as_dict() for _, entry in sorted(reg.retargeters.items())]
    failures = [
        {"plugin": f.name, "distribution": f.distribution, "version": f.version, "error": f.error}
        for f in reg.failures
    ]
    if args.json:
        print(json.dumps({"retargeters": rows, "failed_plugins": failures}, indent=2))
        return 0
    if not rows:
        print("no retargeters registered")
    width = max([len(r["name"]) for r in rows] + [4])
    print(f"{'NAME':<{width}}  {'SOURCES':<14} {'OUTPUT':<8} {'EDIT':<4} {'STREAM':<6} ORIGIN")
    for r in rows:
        caps = r["capabilities"]
        print(
            f"{r['name']:<{width}}  {','.join(caps['sources']):<14} {caps['outputs']:<8} "
            f"{'yes' if caps['edit'] else '-':<4} {'yes' if caps['stream'] else '-':<6} "
            f"{'built-in' if r['builtin'] else r['origin']}"
        )
        if r["summary"]:
            print(f"{'':<{width}}  {r['summary']}")
    if failures:
        print("\nplugins that failed to load:")
        for f in failures:
            print(f"  {f['plugin']} ({f['distribution']} {f['version']}): {f['error']}")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from .registry import catalogue

    entry = catalogue().resolve(args.name)  # its manifest: no plugin code imported
    params = entry.parameters
    if args.json:
        data = entry.as_dict()
        data["parameters"] = {
            k: {"default": jsonable(p.default), "valid": p.valid, "doc": p.doc}
            for k, p in params.items()
        }
        print(json.dumps(data, indent=2))
        return 0
    caps = entry.capabilities
    print(f"{entry.name}  ({'built-in' if entry.plugin.builtin else entry.plugin.origin})")
    if entry.aliases:
        print(f"aliases: {', '.join(entry.aliases)}")
    if entry.paper:
        print(f"paper:   {entry.paper}")
    if entry.summary:
        print(f"summary: {entry.summary}")
    needs = ", ".join(" or ".join(n) if isinstance(n, tuple) else n for n in caps.needs) or "-"
    print(f"sources: {', '.join(caps.sources)}    needs: {needs}    output: {caps.outputs}")
    print(f"stream: {'yes' if caps.stream else 'no'}    edit: {'yes' if caps.edit else 'no'}")
    print("parameters:")
    if not params:
        print("  (none)")
    for k, p in params.items():
        print(f"  {k} = {p.default!r}" + (f"    ({p.valid})" if p.valid else ""))
        if p.doc:
            print(f"      {p.doc}")
    return 0


def cmd_formats(args: argparse.Namespace) -> int:
    from .io import formats, shadow_note

    rows = formats()
    for direction, title in (("read", "readers:"), ("write", "writers:")):
        print(title)
        for row in sorted(
            (r for r in rows if r["direction"] == direction), key=lambda r: r["name"]
        ):
            if not row["builtin"]:
                origin = f" [{row['origin']}, priority {row['priority']:g}]"
            else:  # a built-in below (or above) the others says so: the meshio formats are at -1
                origin = f" [priority {row['priority']:g}]" if row["priority"] else ""
            print(
                f"  {row['name']:<14} {row['kind']:<14} {' '.join(row['extensions']):<20} {row['description']}{origin}"
            )
            note = shadow_note(row)
            if note:
                print(f"  {'':<14} {'':<14} {'':<20} -> {note}")
    return 0


#: Source and target parts a method may need -> the ``run`` option that gives them.
RUN_OPTIONS = {
    "landmarks": "--landmarks FILE (target landmark vertex ids)",
    "source_landmarks": "--source-landmarks FILE (source landmark vertex ids; a markers source needs none)",
    "feature_lines": "--feature-lines JSON",
    "source_feature_lines": "--source-feature-lines JSON",
    "examples": "--examples FILE",
    "source_examples": "--source-examples FILE",
    "layers": "--layers NPZ",
    "actor_layers": "--actor-layers NPZ",
    "blendshapes": "a --target with blendshapes (a glb with morph targets, a rig folder or a rig .npz)",
    "source_rig": "--source-rig FILE",
}


def _run_inputs(args: argparse.Namespace) -> list[str]:
    """Every file ``run`` reads (the output may be none of them)."""
    names = (
        "source",
        "target",
        "topology",
        "source_neutral",
        "source_landmarks",
        "source_feature_lines",
        "source_examples",
        "source_rig",
        "source_head_motion",
        "actor_layers",
        "landmarks",
        "feature_lines",
        "examples",
        "layers",
    )
    return [getattr(args, n) for n in names if getattr(args, n, None)]


def _read_layers(path: str, option: str) -> LayeredRig:
    from .io.bundle import read_npz_object
    from .model import LayeredRig

    obj = read_npz_object(Path(path))
    if not isinstance(obj, LayeredRig):
        raise FileFormatError(
            f"{path}: {option} needs a faceretarget layers .npz (faceretarget.io.save(layered_rig, 'x.npz')), this file holds a {type(obj).__name__}"
        )
    return obj


def load_run_source(args: argparse.Namespace) -> Source:
    """The :class:`~faceretarget.model.Source` of ``run``: the --source file with the parts
    given by the --source-* options (which replace a bundle's)."""
    from . import io
    from .model import Mesh, MeshSequence

    options = {k: v for k, v in (("topology", args.topology), ("fps", args.fps)) if v is not None}
    neutral = None
    if args.source_neutral:
        neutral = io.load(args.source_neutral, kind="mesh")
        options.setdefault("topology", neutral)
    source = io.load_source(args.source, kind=args.source_kind, rig=args.source_rig, **options)
    changes: dict[str, Any] = {}
    if neutral is not None:
        perf = source.performance
        if not isinstance(perf, MeshSequence):
            raise InputError(
                f"--source-neutral is for mesh-sequence sources; {args.source} holds {source.kind}"
            )
        if neutral.n_vertices != perf.n_vertices:
            raise InputError(
                f"--source-neutral {args.source_neutral} has {neutral.n_vertices} vertices, the source {perf.n_vertices}; they must match one to one"
            )
        changes["performance"] = MeshSequence(
            perf.vertices,
            perf.triangles,
            fps=perf.fps,
            reference=Mesh(neutral.vertices, perf.triangles),
            name=perf.name,
        )
    if args.source_landmarks:
        changes["landmarks"] = io.read_landmarks(args.source_landmarks)
    if args.source_feature_lines:
        changes["feature_lines"] = io.read_feature_lines(args.source_feature_lines)
    if args.source_examples:
        changes["examples"], changes["example_names"] = io._examples(args.source_examples)
    if args.source_head_motion:
        changes["head_motion"] = _read_npy(args.source_head_motion)
    if args.actor_layers:
        changes["actor_layers"] = _read_layers(args.actor_layers, "--actor-layers")
    return source.replace(**changes) if changes else source


def _read_npy(path: str) -> np.ndarray:
    import numpy as np

    from .io._common import guarded_reader, load_npy

    return guarded_reader(lambda p: np.asarray(load_npy(p, mmap=False)))(Path(path))


def load_run_target(args: argparse.Namespace) -> TargetRig:
    """The :class:`~faceretarget.model.TargetRig` of ``run``: --target with its parts from the options."""
    from . import io

    target = io.load_target(
        args.target,
        landmarks=args.landmarks,
        feature_lines=args.feature_lines,
        examples=args.examples,
        kind=args.target_kind,
    )
    if args.layers:
        target = target.replace(layers=_read_layers(args.layers, "--layers"))
    return target


def _check_needs(entry: RetargeterInfo, source: Any, target: Any) -> None:
    """A method that does not apply says what is missing and which option gives it."""
    from .retargeter import _has

    reason = entry.cls.why_not(source, target)
    if reason is None:
        return
    hints = []
    for need in entry.capabilities.needs:
        options: tuple[str, ...] = need if isinstance(need, tuple) else (need,)
        if not any(_has(source, target, n) for n in options):
            hints.append(" or ".join(RUN_OPTIONS.get(n, n) for n in options))
    hint = f"; give {'; '.join(hints)}" if hints else ""
    raise CapabilityError(f"{reason}{hint} (see `faceretarget run --help`)")


def cmd_run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from . import get, io
    from .registry import registry

    params = parse_sets(args.params)
    retargeter = get(args.name, **params)
    inputs = _run_inputs(args)
    _check_output_path(args.out, inputs, args.force)  # before any slow work
    entry = registry().resolve(args.name)
    plugin = entry.plugin
    steps = tqdm(total=5, desc=f"{retargeter.name}", unit="step", disable=None, file=sys.stderr)
    steps.set_postfix_str("reading source")
    source = load_run_source(args)
    steps.update()
    steps.set_postfix_str("reading target")
    target = load_run_target(args)
    _check_needs(entry, source, target)
    steps.update()
    steps.set_postfix_str("fitting")
    t0 = time.perf_counter()
    who = (retargeter.name, plugin)
    _plugin_call(who, "fit", retargeter.fit, source, target)
    steps.update()
    steps.set_postfix_str("retargeting")
    animation = _plugin_call(
        who, "retarget", retargeter.retarget, source
    )  # checked by Retargeter.check_output
    steps.update()
    steps.set_postfix_str("writing")
    io.save(animation, args.out, force=args.force, inputs=inputs)
    steps.update()
    steps.close()
    print(
        f"wrote {args.out}: {animation.n_frames} frames by {retargeter.name} in {time.perf_counter() - t0:.2f} s"
    )
    return 0


def _check_output_path(out: str, inputs: list[str], force: bool) -> None:
    """Refuse an output that is one of the inputs (any spelling or link), or exists without
    --force, before any slow work (``faceretarget.io`` checks again when writing)."""
    from pathlib import Path

    from .io._atomic import check_destination

    check_destination(
        out, inputs=inputs, force=force, folder=not Path(out).suffix or out.endswith(("/", "\\"))
    )


def _plugin_call(
    who: tuple[str, PluginInfo], stage: str, call: Callable[..., _T], *args: Any
) -> _T:
    """``call(*args)`` for ``who = (retargeter name, PluginInfo)``: a failure of a third-party
    plugin (or an invalid output of any) is reported with the plugin's name and distribution."""
    name, plugin = who
    where = f"{name} (plugin {plugin.name!r}, distribution {plugin.origin})"
    ours = plugin.builtin  # a built-in's errors are shown as they are, except an invalid output
    try:
        return call(*args)
    except FaceRetargetError as exc:
        if ours and not isinstance(exc, PluginOutputError):
            raise
        try:
            renamed = type(exc)(f"{where}, {stage}: {exc}")
        except Exception:  # an exception class with another signature: keep it as it is
            raise exc from None
        raise renamed from exc
    except Exception as exc:
        if ours:
            raise
        raise PluginError(
            f"{where} failed in {stage}: {type(exc).__name__}: {_one_line(exc)}"
        ) from exc
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # sys.exit(0) in a plugin is not a success: nothing was written
        raise PluginError(
            f"{where} ended the program in {stage} with {type(exc).__name__}({_exit_arg(exc)}) instead of returning "
            "or raising an error; nothing was written (report this to the plugin's author)"
        ) from exc


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
