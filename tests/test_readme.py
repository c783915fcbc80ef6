"""The README and docs/*.md run as written.

Every ```console / ```sh / ```bash / ```shell block and every ```python block of README.md
and docs/*.md (not docs/methods/, whose blocks are excerpts of the method pages) is run, in
order, in a temporary folder per document that holds the files the examples name, made from a
built-in case by ``faceretarget cases export`` (``FIXTURE_FILES`` says which is which). So a
documented command that fails fails this test, with the document, line and stderr.

Rules for shell blocks (the same for a reader copying them):

- a line starting with ``$ `` is a command and the other lines are its output, when the block
  has such lines; else every line is a command. ``\\`` continues a line; ``#`` starts a comment;
- ``faceretarget ...`` runs (through ``python -m faceretarget.cli`` of this interpreter), in the
  document's folder; ``cd DIR`` changes that folder for the rest of the document;
- ``pip install PATH`` of a folder of this repository installs a copy of it with
  ``--target`` into the document's temporary folder, which is put on ``PYTHONPATH`` of the
  document's later commands (the user's environment is left alone); other installs
  (``pip install -e ".[test]"``) and other programs (``python -m pytest``, benchmarks) are not
  run: they are the test suite or the installation itself;
- a ```toml block preceded by ``<!-- doctest: file NAME -->`` is written to NAME (before the
  document's commands run), so a manifest shown in the docs is the one that runs;
- ``<!-- doctest: skip REASON -->`` before a block skips it with that visible reason (keep rare).

A command that appears, identical, in two documents runs once (the demo takes a minute).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SHELL_LANGS = {"console", "sh", "bash", "shell"}
MARKER = re.compile(r"<!--\s*doctest:\s*(skip|file)\s+(.*?)\s*-->")
#: The case the fixtures are exported from (small, so every documented command is quick).
FIXTURE_CASE = "synthetic-human?resolution=800&n_frames=20"
#: Commands already run by an earlier document (text -> document:line).
_RAN: dict[str, str] = {}


@dataclass
class Block:
    doc: Path
    line: int  # 1-based line of the opening fence
    lang: str
    text: str
    marker: tuple[str, str] | None = None

    @property
    def where(self) -> str:
        return f"{self.doc.relative_to(ROOT)}:{self.line}"


def extract(path: Path) -> list[Block]:
    """The fenced blocks of a markdown file, with the doctest marker just above each."""
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks, i = [], 0
    while i < len(lines):
        m = re.match(r"^```\s*([\w+-]*)\s*$", lines[i])
        if not m:
            i += 1
            continue
        lang, start = m.group(1).lower(), i
        j = i + 1
        while j < len(lines) and not re.match(r"^```\s*$", lines[j]):
            j += 1
        prev = next((lines[k] for k in range(start - 1, -1, -1) if lines[k].strip()), "")
        mk = MARKER.search(prev)
        blocks.append(
            Block(
                path,
                start + 1,
                lang,
                "\n".join(lines[start + 1 : j]) + "\n",
                (mk.group(1), mk.group(2)) if mk else None,
            )
        )
        i = j + 1
    return blocks


def shell_commands(text: str) -> list[list[str]]:
    """The commands of a shell block as argument lists (prompts, output, comments removed)."""
    raw = text.splitlines()
    if any(line.startswith("$ ") for line in raw):
        raw = [line[2:] for line in raw if line.startswith("$ ")]
    joined, buf = [], ""
    for line in raw:
        if line.rstrip().endswith("\\"):
            buf += line.rstrip()[:-1] + " "
            continue
        joined.append(buf + line)
        buf = ""
    if buf:
        joined.append(buf)
    return [words for words in (shlex.split(line, comments=True) for line in joined) if words]


# ---------------------------------------------------------------------------------------
# fixtures: the files the examples name
# ---------------------------------------------------------------------------------------
#: file named in the docs -> file of the export it is (markers files are made from the take)
FIXTURE_FILES = {
    "hero.glb": "character.glb",
    "hero_markers.json": "character_landmarks.json",
    "characters/hero.glb": "character.glb",
    "characters/hero_landmarks.json": "character_landmarks.json",
    "take.pc2": "source.pc2",
    "actor.obj": "source_neutral.obj",
}
MARKER_FILES = ("shot.c3d", "shots/sh010.c3d")
DEFAULT_MANIFEST = """\
[[job]]
shot = "shot.c3d"
character = "hero.glb"
landmarks = "hero_markers.json"
method = "spacetime"
out = "out/shot_hero.glb"
"""


def cli(*args: str, cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "faceretarget.cli", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
    )


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    """A built-in case exported as ordinary files by the command line, plus marker takes."""
    import faceretarget as fr

    folder = tmp_path_factory.mktemp("fixtures") / "exported"
    out = cli("cases", "export", FIXTURE_CASE, str(folder), cwd=folder.parent)
    assert out.returncode == 0, out.stderr
    case = fr.io.load_bundle(folder / "case.npz")
    source = case.source
    ids = np.asarray(source.landmarks.vertex_ids)
    perf = source.performance
    markers = fr.MarkerSequence(
        np.asarray(perf.vertices)[:, ids],
        names=list(source.landmarks.names),
        fps=perf.fps,
        reference=perf.reference.vertices[ids],
    )
    fr.save(markers, folder / "markers.c3d")
    return folder


def populate(folder: Path, exported: Path) -> None:
    shutil.copytree(exported, folder / "exported")
    for name, part in FIXTURE_FILES.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(exported / part, folder / name)
    for name in MARKER_FILES:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(exported / "markers.c3d", folder / name)
    (folder / "out").mkdir()
    (folder / "shots.toml").write_text(DEFAULT_MANIFEST)


# ---------------------------------------------------------------------------------------
# running a document
# ---------------------------------------------------------------------------------------
@dataclass
class Session:
    cwd: Path
    site: Path
    env: dict = field(default_factory=dict)
    log: list[str] = field(default_factory=list)

    def pip_install(self, words: list[str], block: Block) -> None:
        targets = [w for w in words[2:] if not w.startswith("-")]
        local = [
            (ROOT / t)
            for t in targets
            if (ROOT / t).is_dir() and (ROOT / t).resolve().is_relative_to(ROOT)
        ]
        if not local or (ROOT / targets[0]).resolve() == ROOT:
            self.log.append(
                f"{block.where}: not run (installation of the project itself): {shlex.join(words)}"
            )
            return
        for src in local:  # build from a copy: nothing is written into the checkout
            copy = self.site.parent / f"src-{src.name}"
            shutil.copytree(
                src, copy, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__")
            )
            out = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "pip",
                    "install",
                    "--no-deps",
                    "--no-build-isolation",
                    "--quiet",
                    "--target",
                    str(self.site),
                    str(copy),
                ],
                capture_output=True,
                text=True,
                cwd=self.site.parent,
            )
            assert out.returncode == 0, (
                f"{block.where}: {shlex.join(words)} (into a temporary --target) failed:\n{out.stderr[-3000:]}"
            )
        self.log.append(
            f"{block.where}: installed a copy into a temporary --target folder: {shlex.join(words)}"
        )
        self.env["PYTHONPATH"] = os.pathsep.join(
            filter(None, [str(self.site), self.env.get("PYTHONPATH", "")])
        )

    def run_shell(self, block: Block) -> None:
        for words in shell_commands(block.text):
            line = shlex.join(words)
            if words[0] == "cd":
                self.cwd = (self.cwd / words[1]).resolve()
                assert self.cwd.is_dir(), f"{block.where}: `{line}`: no such folder"
            elif words[:2] == ["pip", "install"]:
                self.pip_install(words, block)
            elif words[0] == "faceretarget":
                if line in _RAN:
                    self.log.append(f"{block.where}: ran already at {_RAN[line]}: {line}")
                    continue
                start = time.perf_counter()
                out = cli(*words[1:], cwd=self.cwd, env=self.env)
                assert out.returncode == 0, (
                    f"{block.where}: `{line}` exited {out.returncode} in a folder with {sorted(p.name for p in self.cwd.iterdir())}\n"
                    f"stderr: {out.stderr[-3000:]}\nstdout: {out.stdout[-1500:]}"
                )
                _RAN[line] = block.where
                self.log.append(f"{block.where}: ok ({time.perf_counter() - start:.0f} s): {line}")
            else:
                self.log.append(f"{block.where}: not run (not a faceretarget command): {line}")

    def run_python(self, block: Block) -> None:
        start = time.perf_counter()
        script = self.cwd / f"doc_block_{block.line}.py"
        script.write_text(block.text)
        out = subprocess.run(
            [sys.executable, script.name],
            cwd=self.cwd,
            env=self.env,
            capture_output=True,
            text=True,
        )
        script.unlink()
        assert out.returncode == 0, f"{block.where}: the python block failed:\n{out.stderr[-3000:]}"
        self.log.append(f"{block.where}: ok ({time.perf_counter() - start:.0f} s): python block")


def runnable(block: Block) -> bool:
    return block.lang in SHELL_LANGS or block.lang == "python"


@pytest.mark.parametrize("doc", DOCS, ids=[str(d.relative_to(ROOT)) for d in DOCS])
def test_document_runs_as_written(doc, exported, tmp_path, capsys):
    folder = tmp_path / "work"
    folder.mkdir()
    populate(folder, exported)
    env = dict(os.environ, FACERETARGET_TIMEOUT="600")
    session = Session(folder, tmp_path / "site", env)
    blocks = extract(doc)
    for block in blocks:
        if block.marker and block.marker[0] == "file":
            assert block.lang in ("toml", "json", "text", ""), (
                f"{block.where}: a file marker belongs on a data block"
            )
            (folder / block.marker[1]).write_text(block.text)
    for block in blocks:
        if not runnable(block):
            continue
        if block.marker and block.marker[0] == "skip":
            assert block.marker[1], f"{block.where}: a skip marker needs a reason"
            session.log.append(f"{block.where}: skipped: {block.marker[1]}")
            continue
        (session.run_python if block.lang == "python" else session.run_shell)(block)
    with capsys.disabled():
        print(
            f"\n{doc.relative_to(ROOT)}:\n  " + "\n  ".join(session.log or ["(no runnable blocks)"])
        )


def test_the_extractor_finds_the_readme_commands():
    """The README's blocks are found (a broken extractor would pass every document)."""
    blocks = [b for b in extract(ROOT / "README.md") if runnable(b)]
    commands = [
        shlex.join(c) for b in blocks if b.lang in SHELL_LANGS for c in shell_commands(b.text)
    ]
    assert sum(c.startswith("faceretarget run ") for c in commands) >= 3
    assert "faceretarget demo" in commands
    assert any(c.startswith("faceretarget convert take.pc2 take.glb") for c in commands)
    assert any(b.lang == "python" for b in blocks)
    evaluation = extract(ROOT / "docs" / "evaluation.md")
    assert any(b.marker == ("file", "shots.toml") and "[[job]]" in b.text for b in evaluation)
    assert shell_commands("$ pip install x\nout put\n$ faceretarget list  # c\n") == [
        ["pip", "install", "x"],
        ["faceretarget", "list"],
    ]
    assert shell_commands("faceretarget run a \\\n   --out 'b c'\n") == [
        ["faceretarget", "run", "a", "--out", "b c"]
    ]


def test_skips_are_rare_and_say_why():
    skips = [
        (b.where, b.marker[1])
        for d in DOCS
        for b in extract(d)
        if b.marker and b.marker[0] == "skip"
    ]
    assert all(reason for _, reason in skips), skips
    assert len(skips) <= 2, f"too many skipped doc blocks: {skips}"


def test_nothing_names_a_path_outside_the_repository():
    """Docs, examples and code name no file outside the checkout (another project's data or tools)."""
    pattern = re.compile(r"\.\./shared|/work/|shared/(?:data|checks)/")
    here = Path(__file__).resolve()
    offenders = []
    for path in ROOT.rglob("*"):
        if (
            path.suffix not in {".py", ".md", ".toml", ".txt", ".cfg", ".json"}
            or not path.is_file()
            or path.resolve() == here
        ):
            continue
        rel = path.relative_to(ROOT)
        if any(
            part in {"build", ".git", ".hypothesis", ".pytest_cache"} or part.endswith(".egg-info")
            for part in rel.parts
        ):
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except (UnicodeDecodeError, OSError):
            continue
        offenders += [
            f"{rel}:{n}: {line.strip()[:100]}"
            for n, line in enumerate(text.splitlines(), 1)
            if pattern.search(line)
        ]
    assert not offenders, "paths outside the repository:\n" + "\n".join(offenders)
