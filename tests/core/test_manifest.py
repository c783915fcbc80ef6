"""Manifest first: `list`, `info` and available() read manifests without importing plugin code,
and the registry checks that every class agrees with its manifest."""

import ast
import dataclasses
import importlib
import importlib.util
import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import faceretarget as fr
from faceretarget import errors, manifest
from faceretarget import registry as registry_module
from faceretarget.registry import Registry, read_catalogue


def test_list_info_and_available_import_no_plugin_code():
    code = textwrap.dedent("""
        import contextlib, io, json, sys
        import faceretarget as fr
        from faceretarget import cli
        rows = fr.available()
        with contextlib.redirect_stdout(io.StringIO()) as out:
            assert cli.main(["list"]) == 0
            assert cli.main(["list", "--json"]) == 0
            assert cli.main(["info", "spacetime"]) == 0
            assert cli.main(["info", "seol2012_paper", "--json"]) == 0
        loaded = sorted(m for m in sys.modules if m.startswith("faceretarget.plugins.") or m in ("numba", "scipy.sparse"))
        print(json.dumps({"names": [r["name"] for r in rows], "loaded": loaded, "out": out.getvalue()}))
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout)
    assert result["loaded"] == [], f"listing imported {result['loaded']}"
    assert set(read_catalogue()) <= set(result["names"])
    assert "a finite number in [0, 1e12]" in result["out"], (
        "info shows each parameter's valid values"
    )


def test_info_shows_the_manifest_and_its_constraints(capsys):
    from faceretarget import cli

    assert cli.main(["info", "normalmesh", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    levels = data["parameters"]["levels"]
    assert levels == {
        "default": "auto",
        "valid": "'auto' or a whole number in [0, 7]",
        "doc": manifest.builtin()["normalmesh"].parameters["levels"].doc,
    }
    assert data["parameters"]["base_triangles"]["default"] is None


def test_builtin_classes_take_their_constraints_from_registry_toml():
    reg = fr.registry.registry()
    for name, m in manifest.builtin().items():
        cls = reg.resolve(name).cls
        assert manifest.disagreements(cls, m) == [], name
        declared = fr.validation.constraints_of(cls)
        assert set(declared) == set(m.parameters), (
            f"{name}: parameter_constraints and registry.toml name different parameters"
        )


def test_builtin_classes_have_the_capabilities_and_summary_of_registry_toml():
    reg = fr.registry.registry()
    for name, m in manifest.builtin().items():
        cls = reg.resolve(name).cls
        assert cls.capabilities == m.capabilities, name
        assert cls.summary == m.summary, name
        assert cls.packaged_manifest() == m, name


#: (class name, attribute) a built-in class still states itself (derived from another
#: class's, or a literal equal to the manifest's; the registry checks that they agree).
#: None left; a new entry needs a reason.
STILL_STATED: set[tuple[str, str]] = set()


@pytest.mark.parametrize("name", sorted(manifest.builtin()))
def test_a_builtin_class_takes_what_its_manifest_entry_says(monkeypatch, name):
    """The built-in classes restate neither capabilities nor summary: a fresh copy of the
    class's module, made while the packaged manifest says something else about it, follows."""
    packaged = manifest.builtin()
    m = packaged[name]
    edited = dict(packaged)
    edited[name] = dataclasses.replace(
        m,
        capabilities=dataclasses.replace(m.capabilities, stream=not m.capabilities.stream),
        summary=f"edited: {m.summary}",
    )
    monkeypatch.setattr(manifest, "builtin", lambda: edited)
    module_name = fr.registry.registry().resolve(name).cls.__module__
    copy_name = f"{module_name}_manifest_probe"
    spec = importlib.util.spec_from_file_location(
        copy_name, importlib.import_module(module_name).__file__
    )
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, copy_name, module)
    spec.loader.exec_module(module)
    (cls,) = [
        c
        for c in vars(module).values()
        if isinstance(c, type) and c.__module__ == copy_name and vars(c).get("name") == name
    ]
    for attribute in ("capabilities", "summary"):
        value = getattr(cls, attribute)
        if (name, attribute) in STILL_STATED:
            assert value == getattr(m, attribute), (name, attribute)
        else:
            assert value == getattr(edited[name], attribute), (name, attribute)


def test_no_builtin_class_writes_its_capabilities():
    plugins = Path(importlib.import_module("faceretarget.plugins").__file__).parent
    calls = [
        f"{path.relative_to(plugins)}:{node.lineno}"
        for path in sorted(plugins.rglob("*.py"))
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "Capabilities"
    ]
    assert not calls, f"built-in capabilities come from registry.toml: {calls}"


def test_a_class_outside_the_builtin_package_keeps_what_it_states():
    class Layers(fr.Retargeter):  # a third-party class may reuse a built-in's name
        name = "layers"
        capabilities = fr.Capabilities(sources=("mesh",))
        summary = "mine"

    class Unstated(fr.Retargeter):
        name = "normalmesh"

    assert Layers.packaged_manifest() is None and Unstated.packaged_manifest() is None
    assert Layers.capabilities == fr.Capabilities(sources=("mesh",)) and Layers.summary == "mine"
    assert Unstated.capabilities == fr.Capabilities() and Unstated.summary == ""


def _edited_catalogue(monkeypatch, old: str, new: str):
    text = manifest.builtin_text()
    assert old in text
    edited = text.replace(old, new, 1)
    monkeypatch.setattr(registry_module, "read_catalogue", lambda *a, **k: read_catalogue(edited))


@pytest.mark.parametrize(
    "old, new, words",
    [
        (
            'alpha = { default = 0.01, type = "float", range = "[0, 1e12]"',
            'alpha = { default = 0.02, type = "float", range = "[0, 1e12]"',
            r"plugin 'spacetime'.*hook faceretarget_retargeters.*'alpha': default 0.01 in __init__, 0.02 in the manifest",
        ),
        (
            'alpha = { default = 0.01, type = "float", range = "[0, 1e12]"',
            'alpha = { default = 0.01, type = "float", range = "[0, 1e6]"',
            r"'alpha': class accepts a finite number in \[0, 1e12\], the manifest a finite number in \[0, 1e6\]",
        ),
        (
            'sources = ["mesh"]\nneeds = ["feature_lines"',
            'sources = ["markers"]\nneeds = ["feature_lines"',
            r"plugin 'coating'.*capabilities",
        ),
        (
            "[retargeters.layers.parameters]\n",
            '[retargeters.layers.parameters]\nwobble = { default = 1, doc = "d" }\n',
            r"wobble in the manifest but not in __init__",
        ),
    ],
)
def test_a_builtin_class_that_disagrees_with_registry_toml_is_an_error(
    monkeypatch, old, new, words
):
    _edited_catalogue(monkeypatch, old, new)
    with pytest.raises(errors.PluginLoadError, match=words):
        Registry().load()


# -- third-party plugins with a manifest in their package -------------------------------------
PLUGIN = """
import faceretarget as fr
from faceretarget.validation import Interval

class Echo(fr.Retargeter):
    name = "echo"
    capabilities = fr.Capabilities(sources=("mesh",))
    parameter_constraints = {"gain": [Interval(float, 0, None)]}
    def __init__(self, *, gain=1.0):
        self.gain = gain
    def _fit(self, source, target):
        pass
    def _retarget(self, source):
        pass

@fr.hookimpl
def faceretarget_retargeters():
    return [Echo]
"""

MANIFEST = """
[retargeters.echo]
summary = "echoes"
aliases = ["echo2024"]
[retargeters.echo.capabilities]
sources = ["mesh"]
[retargeters.echo.parameters]
gain = { default = 1.0, type = "float", range = "[0, inf)", doc = "how loud" }
"""


@pytest.fixture
def echo_dist(tmp_path, monkeypatch):
    """A fake installed distribution ``echo-dist`` whose package ``echo_pkg`` ships faceretarget.toml."""

    def make(manifest_text: str = MANIFEST):
        site = tmp_path / "site"
        (site / "echo_pkg").mkdir(parents=True)
        (site / "echo_pkg" / "__init__.py").write_text(PLUGIN)
        (site / "echo_pkg" / "faceretarget.toml").write_text(manifest_text)
        info = site / "echo_dist-0.1.dist-info"
        info.mkdir()
        (info / "METADATA").write_text("Metadata-Version: 2.1\nName: echo-dist\nVersion: 0.1\n")
        (info / "entry_points.txt").write_text("[faceretarget]\necho = echo_pkg\n")
        monkeypatch.syspath_prepend(str(site))
        importlib.invalidate_caches()
        monkeypatch.delitem(sys.modules, "echo_pkg", raising=False)
        return site

    return make


def test_a_plugin_manifest_is_listed_without_importing_the_plugin(echo_dist):
    echo_dist()
    index = Registry().index()
    entry = index.resolve("echo2024")
    assert (
        entry.name == "echo"
        and entry.summary == "echoes"
        and entry.plugin.distribution == "echo-dist"
    )
    assert entry.parameters["gain"].valid == "a finite number >= 0"
    assert "echo_pkg" not in sys.modules, "the index imported the plugin"
    loaded = Registry().load()
    assert loaded.resolve("echo").cls.__name__ == "Echo" and not loaded.failures


@pytest.mark.parametrize(
    "old, new, words",
    [
        ("default = 1.0", "default = 2.0", r"'gain': default 1.0 in __init__, 2.0 in the manifest"),
        (
            'range = "[0, inf)"',
            'range = "[1, inf)"',
            r"'gain': class accepts a finite number >= 0, the manifest a finite number >= 1",
        ),
        ('sources = ["mesh"]', 'sources = ["markers"]', "capabilities"),
        (
            "[retargeters.echo]",
            '[retargeters.ghost]\nsummary = "s"\n[retargeters.echo]',
            "declares 'ghost' but hook faceretarget_retargeters returned no such class",
        ),
        ("gain = {", "[", "not valid TOML"),
    ],
)
def test_a_plugin_that_disagrees_with_its_manifest_is_skipped_naming_the_mismatch(
    echo_dist, old, new, words
):
    echo_dist(MANIFEST.replace(old, new))
    loaded = Registry().load()
    assert "echo" not in loaded.retargeters
    (failure,) = loaded.failures
    assert failure.name == "echo" and failure.distribution == "echo-dist"
    assert re.search(words, failure.error), failure.error


def test_a_plugin_without_a_manifest_is_described_by_its_class(tmp_path, monkeypatch):
    site = tmp_path / "site"
    site.mkdir()
    (site / "echo_mod.py").write_text(PLUGIN)
    info = site / "echo_mod-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: echo-mod\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[faceretarget]\necho = echo_mod\n")
    monkeypatch.syspath_prepend(str(site))
    importlib.invalidate_caches()
    entry = Registry().index().resolve("echo")  # imported: nothing else describes it
    assert entry.parameters["gain"].valid == "a finite number >= 0" and entry.defaults == {
        "gain": 1.0
    }
    monkeypatch.delitem(sys.modules, "echo_mod", raising=False)


@pytest.mark.parametrize(
    "constraints, words",
    [
        ({"nope": ["boolean"]}, "parameter_constraints names 'nope', which __init__ does not take"),
        (
            {"gain": [fr.validation.Interval(float, 0, 1)]},
            r"the default gain=2.0 is not a finite number in [0, 1]",
        ),
        ({"gain": ["bool"]}, "parameter_constraints: unknown parameter constraint 'bool'"),
    ],
)
def test_a_class_whose_constraints_are_inconsistent_is_refused_at_registration(constraints, words):
    class Bad(fr.Retargeter):
        name = "bad"
        parameter_constraints = constraints

        def __init__(self, *, gain=2.0):
            self.gain = gain

    class Hooks:
        @fr.hookimpl
        def faceretarget_retargeters(self):
            return [Bad]

    loaded = Registry().load(extra=[("bad", Hooks())])
    (failure,) = loaded.failures
    assert "plugin 'bad'" in failure.error and "hook faceretarget_retargeters" in failure.error
    assert words in failure.error, failure.error
