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
from collections.abc import Callable, Iterable
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .._json import jsonable
from ..errors import OutputError
from ..hookspecs import DATA_KINDS

if TYPE_CHECKING:
    import numpy.typing as npt

    from .._types import PathLike
    from ..cases import Case
    from ..model import Landmarks, Source, TargetRig

__all__ = [
    "add_convert_arguments",
    "run_convert",
    "convert",
    "export_case",
    "add_cases_arguments",
    "run_cases",
    "run_commands",
]


def add_convert_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``convert`` arguments to ``parser``."""
    parser.add_argument("input", metavar="IN", help="file or folder to read")
    parser.add_argument(
        "output", metavar="OUT", help="file to write (no extension: a folder of OBJ files)"
    )
    parser.add_argument(
        "--kind",
        choices=DATA_KINDS,
        default=None,
        help="what to read IN as, when its extension is ambiguous",
    )
    parser.add_argument(
        "--force", action="store_true", help="replace OUT if it exists (never an input)"
    )
    parser.add_argument(
        "--topology",
        metavar="MESH",
        default=None,
        help="mesh giving the triangles of a point cache or .npy",
    )
    parser.add_argument(
        "--fps", type=float, default=None, help="frame rate for formats that do not store it"
    )
    return parser


def _same_path(a: Path, b: Path) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def convert(
    src: PathLike, dst: PathLike, *, kind: str | None = None, force: bool = False, **options: Any
) -> Path:
    """Read ``src`` and write it to ``dst`` (see the module docstring)."""
    from . import load, save

    src, dst = Path(src), Path(dst)
    if _same_path(src, dst):
        raise OutputError(f"{dst}: input and output are the same file; choose another output path")
    obj = load(src, kind=kind, **{k: v for k, v in options.items() if v is not None})
    return save(obj, dst, force=force, inputs=[src])


def run_convert(args: argparse.Namespace) -> int:
    """Run ``faceretarget convert`` from parsed arguments; returns the exit code (0)."""
    out = convert(
        args.input,
        args.output,
        kind=args.kind,
        force=args.force,
        topology=args.topology,
        fps=args.fps,
    )
    print(f"wrote {out}")
    return 0


# ---------------------------------------------------------------------------------------
# faceretarget cases export NAME DIR
# ---------------------------------------------------------------------------------------
def _landmarks_json(lm: Landmarks) -> dict:
    data: dict = {}
    if lm.vertex_ids is not None:
        data["vertex_ids"] = jsonable(lm.vertex_ids)
    else:
        data["triangle_ids"] = jsonable(lm.triangle_ids)
        data["barycentric"] = jsonable(lm.barycentric)
    if lm.names is not None:
        data["names"] = [str(n) for n in lm.names]
    return data


def export_case(case: Case | str, folder: PathLike, *, force: bool = False) -> dict[str, Path]:
    """Write ``case`` (a :class:`faceretarget.cases.Case` or a case spec such as
    ``"synthetic-human?n_frames=40"``) as ordinary files in ``folder`` (created; it must be
    new or empty unless ``force``), and return ``{part: path}``.

    Files (each only when the case has the part; ``source_*`` for the performer,
    ``character_*`` for the target):

    - ``source.pc2`` + ``source_neutral.obj`` (mesh sequence: point cache + the actor's
      neutral mesh, which also gives the triangles), ``source.trc`` (markers) or
      ``source.csv`` + ``source_rig.glb`` (weight curves); ``source_head_motion.npy``;
    - ``character.glb`` (neutral + morph targets) or ``character.obj`` (a mesh);
    - ``{source,character}_landmarks.json`` (``{"vertex_ids", "names"}``),
      ``_feature_lines.json`` (``{line: [vertex ids]}``), ``_examples.npz``
      (``examples`` (M, V, 3), ``example_names``), ``_layers.npz`` (faceretarget layers npz);
    - ``truth.npz``: the ground-truth animation (faceretarget npz);
    - ``case.npz``: the whole case as one bundle (``--source case.npz --target case.npz``);
    - ``batch.toml``: one job per applicable method (``faceretarget batch batch.toml``);
    - ``README.txt``: the files and one ``faceretarget run`` command per applicable method.
    """
    import json

    import numpy as np

    from . import save
    from ._atomic import atomic_file, write_bytes
    from .bundle import write_npz

    if isinstance(case, str):
        from ..evaluation.harness import resolve_case

        case = resolve_case(case)
    folder = Path(folder)
    if folder.exists() and (not folder.is_dir() or (any(folder.iterdir()) and not force)):
        raise OutputError(
            f"{folder} already exists and is not an empty folder; choose a new folder or pass --force to replace the files in it"
        )
    folder.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}

    def put(part: str, name: str, write: Callable[[Path], object]) -> None:
        path = folder / name
        write(path)
        written[part] = path

    def put_json(part: str, name: str, data: object) -> None:
        put(
            part,
            name,
            lambda p: write_bytes(p, (json.dumps(data, indent=1) + "\n").encode(), force=force),
        )

    def put_examples(part: str, name: str, examples: npt.ArrayLike, names: Iterable[str]) -> None:
        def write(p: Path) -> None:
            with atomic_file(p, force=force) as fh:
                np.savez(
                    fh,
                    examples=np.asarray(examples),
                    example_names=np.array([str(n) for n in names], dtype=str),
                )

        put(part, name, write)

    source, target = case.source, case.target
    perf = source.performance
    if source.kind == "mesh":
        put("source", "source.pc2", lambda p: save(perf, p, force=force))
        put("source_neutral", "source_neutral.obj", lambda p: save(perf.reference, p, force=force))
    elif source.kind == "markers":
        put("source", "source.trc", lambda p: save(perf, p, force=force))
    else:
        put("source", "source.csv", lambda p: save(perf, p, force=force))
    if source.rig is not None and source.kind == "weights":
        put("source_rig", "source_rig.glb", lambda p: save(source.rig, p, force=force))
    head_motion = source.head_motion
    if head_motion is not None:
        put(
            "source_head_motion",
            "source_head_motion.npy",
            lambda p: _save_npy(p, head_motion, force),
        )
    if target.blendshapes is not None:
        put("character", "character.glb", lambda p: save(target.blendshapes, p, force=force))
    else:
        put("character", "character.obj", lambda p: save(target.neutral, p, force=force))
    for side, obj in (("source", source), ("character", target)):
        if obj.landmarks is not None:
            put_json(f"{side}_landmarks", f"{side}_landmarks.json", _landmarks_json(obj.landmarks))
        if obj.feature_lines:
            put_json(
                f"{side}_feature_lines",
                f"{side}_feature_lines.json",
                {str(k): jsonable(v) for k, v in obj.feature_lines.items()},
            )
        if obj.examples is not None:
            put_examples(
                f"{side}_examples", f"{side}_examples.npz", obj.examples, obj.example_names
            )
        layers = source.actor_layers if side == "source" else target.layers
        if layers is not None:
            put(f"{side}_layers", f"{side}_layers.npz", partial(write_npz, layers, force=force))
    if getattr(case, "truth", None) is not None:
        put("truth", "truth.npz", lambda p: write_npz(case.truth, p, force=force))
    put("case", "case.npz", lambda p: write_npz(case, p, force=force))
    methods = _applicable(source, target)
    (folder / "out").mkdir(exist_ok=True)  # where the run commands and the manifest write
    put(
        "manifest",
        "batch.toml",
        lambda p: write_bytes(p, _manifest(methods, case).encode(), force=force),
    )
    put(
        "readme",
        "README.txt",
        lambda p: write_bytes(p, _export_readme(case, written, methods).encode(), force=force),
    )
    return written


def _save_npy(path: Path, array: npt.ArrayLike, force: bool) -> None:
    import numpy as np

    from ._atomic import atomic_file

    with atomic_file(path, force=force) as fh:
        np.save(fh, np.asarray(array), allow_pickle=False)


def _applicable(source: Source, target: TargetRig) -> list[str]:
    """The methods the exported manifest and README.txt list: from the registry's manifests,
    one per paper (the first the manifests list, ``registry.toml`` order first: a paper's
    variants and ablations are left out, its baselines from other papers are not), each
    when it applies to (source, target). The registry is imported here, at call time: no
    io module imports it when imported (``tests/io/test_layering.py``)."""
    from ..registry import registry

    reg = registry()
    order = {name: i for i, name in enumerate(reg.manifests)}
    infos = sorted(reg.retargeters.values(), key=lambda info: order.get(info.name, len(order)))
    papers: set[str] = set()
    methods = []
    for info in infos:
        paper = info.paper or info.name
        if paper in papers:
            continue
        papers.add(paper)
        if info.cls.why_not(source, target) is None:
            methods.append(info.name)
    return methods


def _manifest(methods: list[str], case: Case) -> str:
    lines = [
        f"# faceretarget batch manifest for the exported case {getattr(case, 'name', '')!r}:",
        "#   faceretarget batch batch.toml",
        "# Paths are relative to this file. case.npz is the whole case as one bundle (the source with its",
        "# landmarks, feature lines, examples and layers; the character with its own), so every method has",
        "# what it needs. See `faceretarget cases export --help` and README.txt for the same on plain files.",
        "",
        "[defaults]",
        'shot = "case.npz"',
        'character = "case.npz"',
    ]
    for m in methods:
        lines += ["", "[[job]]", f'method = "{m}"', f'out = "out/{m}.glb"']
    return "\n".join(lines) + "\n"


def run_commands(written: dict[str, Path], methods: list[str]) -> list[str]:
    """One ``faceretarget run`` command per method on the exported plain files (relative paths)."""

    def arg(option: str, part: str) -> str:
        return f" {option} {written[part].name}" if part in written else ""

    source = (
        f"--source {written['source'].name}"
        + arg("--source-neutral", "source_neutral")
        + arg("--source-rig", "source_rig")
        + arg("--source-head-motion", "source_head_motion")
        + arg("--source-landmarks", "source_landmarks")
        + arg("--source-feature-lines", "source_feature_lines")
        + arg("--source-examples", "source_examples")
        + arg("--actor-layers", "source_layers")
    )
    target = (
        f"--target {written['character'].name}"
        + arg("--landmarks", "character_landmarks")
        + arg("--feature-lines", "character_feature_lines")
        + arg("--examples", "character_examples")
        + arg("--layers", "character_layers")
    )
    return [f"faceretarget run {m} {source} {target} --out out/{m}.glb" for m in methods]


def _export_readme(case: Case, written: dict[str, Path], methods: list[str]) -> str:
    name = getattr(case, "name", "case")
    lines = [f"faceretarget case {name!r}, exported as ordinary files.", "", "Files:"]
    for part, path in written.items():
        lines.append(f"  {path.name:<28} {part.replace('_', ' ')}")
    lines.append(f"  {'README.txt':<28} this file")
    lines.append(f"  {'out/':<28} (empty) for the results")
    lines += ["", "Run each method that applies on the plain files (from this folder):", ""]
    lines += [f"  {c}" for c in run_commands(written, methods)]
    lines += [
        "",
        "or all of them from the bundle case.npz:",
        "",
        "  faceretarget batch batch.toml",
        "",
    ]
    return "\n".join(lines)


def add_cases_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """``faceretarget cases list`` and ``faceretarget cases export NAME DIR``."""
    sub = parser.add_subparsers(
        dest="cases_command", metavar="ACTION", required=True, help="list or export"
    )
    sub.add_parser(
        "list",
        help="the built-in cases",
        description="List the built-in cases (names for compare, batch and export).",
    )
    p = sub.add_parser(
        "export",
        help="write a built-in case as ordinary files",
        description="Write a built-in case as ordinary files: the source take, the target character, landmarks, feature "
        "lines, example poses and layers of both, the ground truth, the whole case as one bundle (case.npz), a "
        "ready batch manifest (batch.toml) and README.txt with a `faceretarget run` command per method.",
        epilog='example: faceretarget cases export "synthetic-human?n_frames=40" take/',
    )
    p.add_argument(
        "name",
        metavar="NAME",
        help="case name, optionally with keywords: synthetic-human, synthetic-stylized, ict, cross_rig, cross_topology; e.g. 'ict?n_frames=40'",
    )
    p.add_argument(
        "folder",
        metavar="DIR",
        type=Path,
        help="folder to write (created; must be new or empty unless --force)",
    )
    p.add_argument(
        "--frames",
        type=int,
        metavar="N",
        help="frames of the performance (same as NAME?n_frames=N)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="write into a folder that is not empty, replacing the files of the export",
    )
    return parser


def run_cases(args: argparse.Namespace) -> int:
    """Run ``faceretarget cases ...``; returns the exit code."""
    from ..errors import ConfigError
    from ..evaluation.harness import CASE_NAMES

    if args.cases_command == "list":
        for name, (factory, fixed) in CASE_NAMES.items():
            keywords = ", ".join(f"{k}={v!r}" for k, v in fixed.items())
            print(f"{name:<20} faceretarget.cases.{factory}({keywords})")
        return 0
    spec = args.name
    if args.frames is not None:
        if args.frames < 3:
            raise ConfigError(f"--frames must be at least 3, got {args.frames}")
        spec += ("&" if "?" in spec else "?") + f"n_frames={args.frames}"
    written = export_case(spec, args.folder, force=args.force)
    print(f"wrote {len(written)} files into {args.folder}:")
    for part, path in written.items():
        print(f"  {path.name:<28} {part.replace('_', ' ')}")
    print(
        f"see {written['readme']} for a `faceretarget run` command per method, or: faceretarget batch {written['manifest']}"
    )
    return 0
