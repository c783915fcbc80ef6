"""The plugin registry: built-ins through entry points, third-party isolation, registry.toml."""

import importlib
import os
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest

import faceretarget as fr
from faceretarget import errors
from faceretarget.hookspecs import HOOK_NAMES
from faceretarget.registry import Registry, read_catalogue

ROOT = Path(__file__).resolve().parents[2]

GOOD_PLUGIN = """
import faceretarget as fr

class Echo(fr.Retargeter):
    name = "{name}"
    capabilities = fr.Capabilities(sources=("mesh",))
    def __init__(self, *, gain=1.0):
        self.gain = gain
    def _fit(self, source, target):
        self.neutral_ = target.neutral.vertices
    def _retarget(self, source):
        import numpy as np
        return fr.Animation(vertices=np.repeat(self.neutral_[None], source.n_frames, axis=0))

@fr.hookimpl
def faceretarget_retargeters():
    return [Echo]
"""


def make_dist(tmp_path, dist, modules: dict, entry_points: dict) -> Path:
    """A fake installed distribution on a temporary sys.path entry."""
    site = tmp_path / f"site_{dist}"
    site.mkdir()
    info = site / f"{dist}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    lines = "\n".join(f"{k} = {v}" for k, v in entry_points.items())
    (info / "entry_points.txt").write_text(f"[faceretarget]\n{lines}\n")
    for name, code in modules.items():
        (site / f"{name}.py").write_text(textwrap.dedent(code))
    return site


@pytest.fixture
def on_path(monkeypatch):
    def add(site: Path):
        monkeypatch.syspath_prepend(str(site))
        importlib.invalidate_caches()

    return add


def test_unknown_name_lists_valid_choices():
    with pytest.raises(errors.UnknownNameError) as info:
        fr.get("no-such")
    assert "valid choices" in str(info.value)
    for name in fr.registry.registry().retargeters:
        assert name in str(info.value)


def test_unknown_parameter_is_named():
    names = list(fr.registry.registry().retargeters)
    if not names:
        pytest.skip("no retargeters registered")
    with pytest.raises(errors.UnknownNameError, match="no parameter"):
        fr.get(names[0], no_such_parameter=1)


def test_third_party_plugin_loads_and_broken_ones_are_recorded(tmp_path, on_path):
    site = make_dist(
        tmp_path,
        "thirdparty",
        {
            "tp_good": GOOD_PLUGIN.format(name="echo_tp"),
            "tp_broken": "raise RuntimeError('boom at import')\n",
            "tp_exit": "import sys\nsys.exit(3)\n",
            "tp_typo": "import faceretarget as fr\n@fr.hookimpl\ndef faceretarget_retargeter():\n    return []\n",
            "tp_notclass": "import faceretarget as fr\n@fr.hookimpl\ndef faceretarget_retargeters():\n    return [42]\n",
            "tp_raises": "import faceretarget as fr\n@fr.hookimpl\ndef faceretarget_retargeters():\n    raise ValueError('hook failed')\n",
        },
        {
            "good": "tp_good",
            "broken": "tp_broken",
            "exits": "tp_exit",
            "typo": "tp_typo",
            "notclass": "tp_notclass",
            "raises": "tp_raises",
        },
    )
    on_path(site)
    reg = Registry().load()
    assert "echo_tp" in reg.retargeters
    assert reg.retargeters["echo_tp"].plugin.distribution == "thirdparty"
    failed = {f.name: f.error for f in reg.failures}
    assert set(failed) == {"broken", "exits", "typo", "notclass", "raises"}
    assert "boom at import" in failed["broken"]
    assert "faceretarget_retargeter" in failed["typo"]
    assert "not a faceretarget.Retargeter" in failed["notclass"]
    assert "hook failed" in failed["raises"]
    assert all(f.distribution == "thirdparty" for f in reg.failures)


def test_duplicate_names_are_an_error_naming_both_origins(tmp_path, on_path):
    on_path(make_dist(tmp_path, "dupa", {"dup_a": GOOD_PLUGIN.format(name="twin")}, {"a": "dup_a"}))
    on_path(make_dist(tmp_path, "dupb", {"dup_b": GOOD_PLUGIN.format(name="twin")}, {"b": "dup_b"}))
    reg = Registry().load()
    assert "twin" in reg.retargeters
    (failure,) = [f for f in reg.failures if f.name in ("a", "b")]
    assert (
        "already registered" in failure.error
        and "dupa" in failure.error
        and "dupb" in failure.error
    )


def test_disable_and_allowlist_environment(tmp_path, on_path, monkeypatch):
    on_path(
        make_dist(
            tmp_path,
            "envplug",
            {"env_mod": GOOD_PLUGIN.format(name="echo_env")},
            {"envp": "env_mod"},
        )
    )
    monkeypatch.setenv("FACERETARGET_DISABLE_PLUGINS", "1")
    assert "echo_env" not in Registry().load().retargeters
    monkeypatch.delenv("FACERETARGET_DISABLE_PLUGINS")
    monkeypatch.setenv("FACERETARGET_PLUGINS", "someone_else")
    assert "echo_env" not in Registry().load().retargeters
    monkeypatch.setenv("FACERETARGET_PLUGINS", "envplug")
    assert "echo_env" in Registry().load().retargeters


def test_trace_environment_prints_hook_calls():
    env = dict(os.environ, FACERETARGET_TRACE="1")
    # fr.available() reads manifests and calls no hook; loading the plugins does
    out = subprocess.run(
        [sys.executable, "-c", "import faceretarget as fr; fr.registry.registry()"],
        capture_output=True,
        text=True,
        env=env,
    )
    assert out.returncode == 0, out.stderr
    assert "faceretarget_retargeters" in out.stderr


def test_available_does_not_import_numba():
    code = "import sys, faceretarget as fr; fr.available(); fr.get(fr.available()[0]['name']) if fr.available() else None; print('numba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False", (
        "listing or constructing retargeters must not import numba"
    )


def test_registry_toml_agrees_with_entry_points_and_classes():
    import importlib.metadata as md

    catalogue = read_catalogue()
    ours = {
        ep.name: ep
        for ep in md.entry_points(group="faceretarget")
        if ep.dist and ep.dist.metadata["Name"] == "faceretarget"
    }
    reg = fr.registry.registry()
    builtin = {n: e for n, e in reg.retargeters.items() if e.plugin.builtin}
    assert set(catalogue) == set(builtin), (
        "registry.toml and the built-in plugins must list the same retargeters"
    )
    for name, entry in catalogue.items():
        assert entry["entry_point"] in ours, (
            f"{name}: entry point {entry['entry_point']!r} not in pyproject.toml"
        )
        info = builtin[name]
        assert info.plugin.name == entry["entry_point"], (
            f"{name} is provided by {info.plugin.name}, registry.toml says {entry['entry_point']}"
        )
        assert fr.Capabilities.from_dict(entry["capabilities"]) == info.cls.capabilities, (
            f"{name}: capabilities differ"
        )
        defaults = info.cls.default_params()
        assert set(entry["parameters"]) == set(defaults), (
            f"{name}: documented parameters differ from __init__'s"
        )
        for p, spec in entry["parameters"].items():
            assert spec.get("doc"), f"{name}.{p} has no doc"
            assert (
                spec.get("default") == defaults[p]
                or (spec.get("default") is None and defaults[p] is None)
                or ("default" not in spec and defaults[p] is None)
            ), (
                f"{name}.{p}: registry.toml default {spec.get('default')!r} != class default {defaults[p]!r}"
            )
        for alias in entry["aliases"]:
            assert fr.info(alias).name == name


@pytest.mark.parametrize(
    "text",
    [
        "not [valid toml",
        "[other]\nx = 1\n",
        "[retargeters.a]\nsummary = 1\n",
        "[retargeters]\na = 3\n",
        '[retargeters.a]\nentry_point="a"\nsummary="s"\npaper="p"\naliases="x"\n',
        '[retargeters.a]\nentry_point="a"\nsummary="s"\npaper="p"\n[retargeters.a.parameters]\nx = 1\n',
    ],
)
def test_malformed_registry_toml_is_a_config_error(text):
    with pytest.raises(errors.ConfigError, match="registry.toml"):
        read_catalogue(text)


def test_every_hook_is_documented():
    doc = (ROOT / "docs" / "plugins.md").read_text()
    for hook in HOOK_NAMES:
        assert f"`{hook}" in doc, f"hook {hook} is not documented in docs/plugins.md"


def test_wheel_ships_registry_toml_and_reads_it_from_there(tmp_path, source_copy):
    project = source_copy(ROOT)  # built from a copy: no build/ or *.egg-info in the checkout
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "build",
            "--wheel",
            "--no-isolation",
            "--outdir",
            str(tmp_path / "dist"),
            str(project),
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("faceretarget-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        assert "faceretarget/registry.toml" in names
        assert zf.read("faceretarget/registry.toml") == (ROOT / "registry.toml").read_bytes()
        assert any(n.startswith("faceretarget/plugins/") for n in names)
        zf.extractall(tmp_path / "unpacked")
    code = (
        "import faceretarget, faceretarget.registry as r; from importlib import resources; "
        "p = resources.files('faceretarget').joinpath('registry.toml'); print(p); r.read_catalogue()"
    )
    env = dict(os.environ, PYTHONPATH=str(tmp_path / "unpacked"))
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tmp_path
    )
    assert run.returncode == 0, run.stderr
    assert str(tmp_path / "unpacked") in run.stdout


def test_readme_method_sections_match_registry_toml():
    out = subprocess.run(
        [sys.executable, str(ROOT / "docs" / "readme_methods.py"), "--check"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    readme = (ROOT / "README.md").read_text()
    for name in read_catalogue():
        if not name.startswith("spacetime_"):
            assert f"### `{name}`" in readme, f"README.md has no section for {name}"
