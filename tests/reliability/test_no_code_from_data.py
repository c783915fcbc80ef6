"""No code from data: nothing in core/ or plugins/ unpickles, evals or shells out on user input,
and plugins come only from installed entry points (filtered by ``FACERETARGET_PLUGINS``).

The source scan parses every module (so aliases like ``from pickle import loads`` and
``import numpy as np`` are followed) and fails on any call that can run code found in a
file, unless the call is in :data:`REVIEWED` with the reason it never sees user data.
Manifest paths that escape their root are covered in ``test_config_fuzz.py``.
"""

import ast
import importlib
import os
import secrets
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pytest
from reliability.fuzzkit import count

from faceretarget import errors
from faceretarget import registry as registry_module
from faceretarget.registry import Registry, read_catalogue

AREA = "source scan"
ROOT = Path(__file__).resolve().parents[2]
SCANNED = ("core", "plugins")

#: call -> why it runs code from data
DANGEROUS = {
    "pickle.load": "unpickling runs code",
    "pickle.loads": "unpickling runs code",
    "pickle.Unpickler": "unpickling runs code",
    "_pickle.load": "unpickling runs code",
    "_pickle.loads": "unpickling runs code",
    "dill.load": "unpickling runs code",
    "dill.loads": "unpickling runs code",
    "cloudpickle.load": "unpickling runs code",
    "cloudpickle.loads": "unpickling runs code",
    "joblib.load": "unpickling runs code",
    "torch.load": "unpickling runs code",
    "pandas.read_pickle": "unpickling runs code",
    "multiprocessing.reduction.ForkingPickler.loads": "unpickling runs code",
    "jsonpickle.decode": "unpickling runs code",
    "marshal.load": "unmarshalling code objects",
    "marshal.loads": "unmarshalling code objects",
    "shelve.open": "shelve unpickles",
    "yaml.unsafe_load": "arbitrary Python objects",
    "yaml.full_load": "Python objects",
    "eval": "evaluates text as code",
    "exec": "executes text as code",
    "compile": "compiles text to code",
    "os.system": "runs a shell",
    "os.popen": "runs a shell",
    "subprocess.getoutput": "runs a shell",
    "subprocess.getstatusoutput": "runs a shell",
    "runpy.run_path": "runs a file",
    "runpy.run_module": "runs a module",
    "importlib.import_module": "imports a module by name",
    "__import__": "imports a module by name",
    "importlib.util.spec_from_file_location": "imports a file",
}
#: method names that are dangerous on any object
DANGEROUS_METHODS = {"load_setuptools_entrypoints": "loads every entry point, unfiltered"}

#: (file, call) -> why this use never sees user data (reviewed by hand)
REVIEWED = {
    ("core/__init__.py", "importlib.import_module"): "lazy submodules from the fixed _LAZY table",
    (
        "core/evaluation/__init__.py",
        "importlib.import_module",
    ): "lazy exports from the fixed _EXPORTS table",
    (
        "core/io/builtin.py",
        "importlib.import_module",
    ): "lazy format modules named by literals in builtin_readers/writers",
    (
        "core/cli.py",
        "importlib.import_module",
    ): "sub-command modules named by literals in build_parser",
    (
        "core/testing.py",
        "pickle.loads",
    ): "round trip of a retargeter pickled one line above (check_clone_pickle)",
    ("core/evaluation/_workers.py", "multiprocessing.reduction.ForkingPickler.loads"): (
        "messages between a supervisor and the worker processes it started, over a private socket pair (as multiprocessing does)"
    ),
}


def dotted(node, aliases) -> str | None:
    """'pickle.loads' for ``pickle.loads`` / ``p.loads`` (import pickle as p) / ``loads`` (from pickle import loads)."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    parts.append(aliases.get(node.id, node.id))
    return ".".join(reversed(parts))


def findings(path: Path, rel: str | None = None):
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    aliases = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                aliases[a.asname or a.name.split(".")[0]] = (
                    a.name if a.asname else a.name.split(".")[0]
                )
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                aliases[a.asname or a.name] = f"{node.module}.{a.name}"
    rel = rel or path.relative_to(ROOT).as_posix()
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        name = dotted(node.func, aliases) or ""
        keywords = {k.arg: k.value for k in node.keywords if k.arg}
        if name in DANGEROUS:
            yield rel, node.lineno, name, DANGEROUS[name]
        method = node.func.attr if isinstance(node.func, ast.Attribute) else ""
        if method in DANGEROUS_METHODS:
            yield rel, node.lineno, method, DANGEROUS_METHODS[method]
        if "allow_pickle" in keywords and not (
            isinstance(keywords["allow_pickle"], ast.Constant)
            and keywords["allow_pickle"].value is False
        ):
            yield (
                rel,
                node.lineno,
                f"{name}(allow_pickle=...)",
                "allow_pickle other than False unpickles",
            )
        if name == "yaml.load":
            loader = keywords.get("Loader") or (node.args[1] if len(node.args) > 1 else None)
            if not (loader is not None and "Safe" in (dotted(loader, aliases) or "")):
                yield rel, node.lineno, name, "yaml.load without SafeLoader builds Python objects"
        if (
            name.startswith("subprocess.")
            and isinstance(keywords.get("shell"), ast.Constant)
            and keywords["shell"].value
        ):
            yield rel, node.lineno, f"{name}(shell=True)", "runs a shell"


def scanned_files():
    return sorted(
        p for d in SCANNED for p in (ROOT / d).rglob("*.py") if "__pycache__" not in p.parts
    )


def test_no_code_from_data_in_the_source_tree():
    files = scanned_files()
    count(AREA, len(files))
    assert len(files) > 20, "the scan found too few modules; is the layout different?"
    bad = [
        f"{rel}:{line}: {call}: {why}"
        for rel, line, call, why in (f for p in files for f in findings(p))
        if (rel, call) not in REVIEWED
    ]
    assert not bad, (
        "calls that can run code from data (review them, or add to REVIEWED with the reason):\n"
        + "\n".join(bad)
    )


def test_the_scanner_finds_what_it_looks_for(tmp_path):
    """The scan itself must not be blind (aliases, np.load keywords, yaml loaders, pluggy)."""
    probe = tmp_path / "probe.py"
    probe.write_text(
        textwrap.dedent("""
        import pickle as p
        import numpy as np
        import yaml
        from marshal import loads
        import subprocess
        p.loads(b"")
        np.load("x", allow_pickle=True)
        np.load("x", allow_pickle=False)
        yaml.load("a: 1")
        yaml.load("a: 1", Loader=yaml.SafeLoader)
        loads(b"")
        eval("1")
        subprocess.run("ls", shell=True)
        self.pm.load_setuptools_entrypoints("faceretarget")
    """)
    )
    found = {call for _, _, call, _ in findings(probe, "probe.py")}
    assert found == {
        "pickle.loads",
        "numpy.load(allow_pickle=...)",
        "yaml.load",
        "marshal.loads",
        "eval",
        "subprocess.run(shell=True)",
        "load_setuptools_entrypoints",
    }, found


# ---------------------------------------------------------------------------------------
# plugins come only from installed entry points
# ---------------------------------------------------------------------------------------
PLUGIN = """
import pathlib
pathlib.Path({marker!r}).write_text("imported")
import faceretarget as fr

@fr.hookimpl
def faceretarget_retargeters():
    return []
"""


def fake_site(
    tmp_path: Path, dist: str, modules: dict[str, str], entry_points: dict[str, str]
) -> Path:
    site = tmp_path / f"site_{dist}"
    info = site / f"{dist}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        "[faceretarget]\n" + "".join(f"{k} = {v}\n" for k, v in entry_points.items())
    )
    for name, code in modules.items():
        (site / f"{name}.py").write_text(code)
    return site


@pytest.fixture
def sites(tmp_path, monkeypatch):
    markers = {n: tmp_path / f"{n}.imported" for n in ("listed", "unlisted", "other")}
    mod = {
        n: f"fr_{n}_{secrets.token_hex(4)}" for n in markers
    }  # fresh module names: nothing cached in sys.modules
    site = fake_site(
        tmp_path,
        "goodplugins",
        {
            mod["listed"]: PLUGIN.format(marker=str(markers["listed"])),
            mod["unlisted"]: PLUGIN.format(marker=str(markers["unlisted"])),
        },
        {"listed": mod["listed"]},
    )
    other = fake_site(
        tmp_path,
        "otherplugins",
        {mod["other"]: PLUGIN.format(marker=str(markers["other"]))},
        {"other": mod["other"]},
    )
    for s in (site, other):
        monkeypatch.syspath_prepend(str(s))
    monkeypatch.delenv("FACERETARGET_PLUGINS", raising=False)
    monkeypatch.delenv("FACERETARGET_DISABLE_PLUGINS", raising=False)
    importlib.invalidate_caches()
    return SimpleNamespace(
        markers=markers, modules=mod, imported=lambda: {n for n, m in markers.items() if m.exists()}
    )


def test_only_entry_points_are_loaded(sites):
    reg = Registry().load()
    count(AREA)
    names = {p.name for p in reg.plugins}
    assert {"listed", "other"} <= names
    assert sites.imported() == {"listed", "other"}, (
        "a module on sys.path without an entry point must never be imported"
    )


@pytest.mark.parametrize("allow", ["listed", "goodplugins", "os,sys", "nothing-installed"])
def test_allow_list_limits_what_is_imported(allow, sites, monkeypatch):
    monkeypatch.setenv("FACERETARGET_PLUGINS", allow)
    reg = Registry().load()
    count(AREA)
    imported = sites.imported()
    expected = {"listed"} if allow in ("listed", "goodplugins") else set()
    assert imported == expected, f"FACERETARGET_PLUGINS={allow!r} imported {imported}"
    assert all(p.builtin or p.name in expected for p in reg.plugins)


def test_catalogue_entry_point_is_never_imported(sites, monkeypatch):
    """registry.toml names entry points; it cannot make the registry import a module."""
    text = f'[retargeters.evil]\nentry_point = "{sites.modules["unlisted"]}"\npaper = "p"\nsummary = "s"\n'
    monkeypatch.setattr(registry_module, "read_catalogue", lambda *a, **k: read_catalogue(text))
    monkeypatch.setenv("FACERETARGET_DISABLE_PLUGINS", "1")
    with pytest.raises(errors.ConfigError, match="no built-in plugin provides it"):
        Registry().load()
    assert not sites.imported()


def test_disable_variable_imports_no_third_party_code(sites, monkeypatch):
    monkeypatch.setenv("FACERETARGET_DISABLE_PLUGINS", "1")
    reg = Registry().load()
    assert not sites.imported()
    assert all(p.builtin for p in reg.plugins) and reg.retargeters
    assert os.environ["FACERETARGET_DISABLE_PLUGINS"] == "1"
