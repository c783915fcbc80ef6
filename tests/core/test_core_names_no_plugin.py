"""The core names no plugin (issue 18 item 4): no string in ``core/**/*.py`` names a built-in
method, and the built-ins' paper reproductions come through the ``faceretarget_presets`` hook."""

import ast
import re
from pathlib import Path

import pytest

import faceretarget
from faceretarget.capabilities import RIG_PARTS, SOURCE_EXTRAS, SOURCE_KINDS
from faceretarget.manifest import builtin
from faceretarget.registry import registry

CORE = Path(faceretarget.__file__).parent

#: Names that are also the core's own words: "layers" is a rig part (TargetRig.layers, a
#: capability need) before it is the method of Kholgade et al.; such a word is not a reference
#: to the plugin.
CORE_WORDS = set(RIG_PARTS) | set(SOURCE_EXTRAS) | set(SOURCE_KINDS)

#: (file relative to core/, name): why it may stay. Keep this short.
ALLOWED = {
    # the technique of Sumner & Popovic 2004, a public function of the geometry package
    # (the method of the same name is built on it, not the other way round)
    ("geometry/deformation_gradients.py", "deformation_transfer"),
    # the Laplacian coating of Sorkine et al. 2004, a geometry operation (the method is named after it)
    ("geometry/local_frames.py", "coating"),
    ("geometry/_laplacian_kernels.py", "coating"),
}


def _method_names() -> set[str]:
    names = set()
    for manifest in builtin().values():
        names.update((manifest.name, *manifest.aliases))
    return {n for n in names if n not in CORE_WORDS}


def _strings(tree: ast.AST):
    """Every string constant of a module (docstrings and f-string parts included)."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            yield node.lineno, node.value


def _hits(text: str, names: set[str]):
    for name in names:
        if re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", text):
            yield name


def test_the_names_come_from_the_manifest():
    names = _method_names()
    assert len(names) >= 10 and "layers" not in names  # the manifest was read; core words left out
    assert all(re.fullmatch(r"[a-z0-9_]+", n) for n in names)


def test_no_core_module_names_a_builtin_method():
    names = _method_names()
    found = []
    for path in sorted(CORE.rglob("*.py")):
        rel = path.relative_to(CORE).as_posix()
        for line, text in _strings(ast.parse(path.read_text(encoding="utf-8"))):
            found += [
                f"core/{rel}:{line}: {name!r}"
                for name in _hits(text, names)
                if (rel, name) not in ALLOWED
            ]
    assert not found, (
        "the core names built-in methods (move it into the plugin, or read it from the manifest):\n"
        + "\n".join(found)
    )


def test_the_check_finds_a_method_name():
    """The scan above sees code strings, docstrings and f-strings alike."""
    source = 'x = "spacetime"\ndef f():\n    """Uses coating."""\n    return f"{x} vs xu2014"\n'
    hits = {n for _, text in _strings(ast.parse(source)) for n in _hits(text, _method_names())}
    assert hits == {"spacetime", "coating", "xu2014"}
    assert not set(_hits("a spacetime-like method; spacetime_editing", _method_names()))


BUILTIN_PRESETS = {
    "coating": {"xu_fig4", "xu_fig6"},
    "layers": {"kholgade_fig8"},
    "normalmesh": {"najung_table1", "najung_fig14"},
    "spacetime": {"seol_fig11"},
}


def test_builtin_presets_come_from_their_plugins_through_the_hook():
    by_plugin: dict[str, set] = {}
    for name, (preset, plugin) in registry().presets.items():
        assert isinstance(preset, faceretarget.Preset) and preset.name == name
        assert preset.claim and preset.setting and preset.title and preset.paper
        assert preset.run.__module__ == f"faceretarget.plugins.{plugin.name}.presets"
        by_plugin.setdefault(plugin.name, set()).add(name)
    assert by_plugin == BUILTIN_PRESETS


def test_baselines_come_from_the_manifest():
    from faceretarget.evaluation._summary import BASELINE, PAPER, method_roles

    declared = {m.name: m.baseline_of for m in builtin().values() if m.baseline_of}
    assert declared, "registry.toml declares no baseline_of"
    roles = method_roles(list(builtin()))
    for name, papers in declared.items():
        assert roles[name].kind == BASELINE and roles[name].baseline_of == papers
        assert all(p in builtin() and roles[p].kind == PAPER for p in papers)


@pytest.mark.parametrize(
    "bad, message",
    [
        ('baseline_of = "coating"', "baseline_of must be a list of strings"),
        ("baseline_of = [1]", "baseline_of must be a list of strings"),
    ],
)
def test_baseline_of_is_checked(bad, message):
    from faceretarget.errors import ConfigError
    from faceretarget.manifest import parse

    text = f'[retargeters.a]\nentry_point = "a"\nsummary = "s"\npaper = "p"\n{bad}\n'
    with pytest.raises(ConfigError, match=message):
        parse(text, "test.toml")
