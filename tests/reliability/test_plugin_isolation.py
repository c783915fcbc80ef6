"""One broken plugin never takes down the rest, and is reported with its name and distribution.

A fake installed distribution ``brokenplugins`` (a ``.dist-info`` folder on a temporary
``sys.path`` entry, as pip would leave it) brings plugins that raise on import, raise in
``fit`` or ``retarget``, return the wrong number of vertices or frames, or NaN, and one
that works. ``faceretarget list``, ``compare``, ``batch`` and ``run`` must go on with
the others, name the culprit and its distribution, and never write a wrong result.
"""
import importlib
import json
import textwrap

import numpy as np
import pytest

import faceretarget as fr
from faceretarget import cli
from faceretarget import registry as registry_module
from faceretarget.registry import Registry
from reliability.fuzzkit import count

AREA = "plugin isolation"
DIST = "brokenplugins"

COMMON = '''
import numpy as np
import faceretarget as fr


class Base(fr.Retargeter):
    capabilities = fr.Capabilities(sources=("mesh", "markers"))

    def __init__(self, *, gain=1.0):
        self.gain = gain

    def _fit(self, source, target):
        self.neutral_ = np.asarray(target.neutral.vertices)

    def _result(self, source, vertices):
        return fr.Animation(vertices=vertices, triangles=None, fps=source.fps)

    def _retarget(self, source):
        return self._result(source, np.repeat(self.neutral_[None], source.n_frames, axis=0))
'''

PLUGINS = {
    "bp_good": "class Good(Base):\n    name = 'bp_good'\nCLS = Good\n",
    "bp_fit": "class Fit(Base):\n    name = 'bp_fit'\n    def _fit(self, source, target):\n        raise RuntimeError('fit exploded')\nCLS = Fit\n",
    "bp_retarget": "class Ret(Base):\n    name = 'bp_retarget'\n    def _retarget(self, source):\n        return 1 / 0\nCLS = Ret\n",
    "bp_vertices": (
        "class Verts(Base):\n    name = 'bp_vertices'\n"
        "    def _retarget(self, source):\n"
        "        return self._result(source, np.repeat(self.neutral_[None, :-1], source.n_frames, axis=0))\nCLS = Verts\n"
    ),
    "bp_frames": (
        "class Frames(Base):\n    name = 'bp_frames'\n"
        "    def _retarget(self, source):\n"
        "        return self._result(source, self.neutral_[None])\nCLS = Frames\n"
    ),
    "bp_nan": (
        "class Nan(Base):\n    name = 'bp_nan'\n"
        "    def _retarget(self, source):\n"
        "        anim = Base._retarget(self, source)\n"
        "        bad = np.array(anim.vertices); bad[0, 0, 0] = np.nan; bad.flags.writeable = False\n"
        "        anim._vertices = bad  # sneaks NaN past the Animation constructor\n"
        "        return anim\nCLS = Nan\n"
    ),
    "bp_type": "class Typ(Base):\n    name = 'bp_type'\n    def _retarget(self, source):\n        return {'vertices': self.neutral_}\nCLS = Typ\n",
}
BAD = ["bp_fit", "bp_retarget", "bp_vertices", "bp_frames", "bp_nan", "bp_type"]


def plugin_module(name: str) -> str:
    return COMMON + PLUGINS[name] + "\n@fr.hookimpl\ndef faceretarget_retargeters():\n    return [CLS]\n"


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The fake distribution on disk: one module per plugin + one that fails to import."""
    root = tmp_path_factory.mktemp("site")
    info = root / f"{DIST}-0.3.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {DIST}\nVersion: 0.3\n")
    modules = {name: plugin_module(name) for name in PLUGINS}
    modules["bp_import"] = "raise RuntimeError('import exploded')\n"
    for name, code in modules.items():
        (root / f"{name}.py").write_text(textwrap.dedent(code))
    (info / "entry_points.txt").write_text("[faceretarget]\n" + "\n".join(f"{n} = {n}" for n in modules) + "\n")
    return root


@pytest.fixture
def reg(site, monkeypatch):
    """A registry loaded with the fake distribution installed, used as the process-wide one."""
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setenv("PYTHONPATH", str(site))  # for spawned batch workers
    monkeypatch.delenv("FACERETARGET_DISABLE_PLUGINS", raising=False)
    monkeypatch.delenv("FACERETARGET_PLUGINS", raising=False)
    importlib.invalidate_caches()
    loaded = Registry().load()
    monkeypatch.setattr(registry_module, "_REGISTRY", loaded)
    return loaded


@pytest.fixture(scope="module")
def case():
    return fr.cases.synthetic(resolution=300, n_frames=4)


def named(text: str, plugin: str) -> bool:
    return plugin in text and DIST in text


def test_import_failure_is_recorded_and_others_load(reg):
    count(AREA)
    failures = {f.name: f for f in reg.failures}
    assert "bp_import" in failures and failures["bp_import"].distribution == DIST
    assert "import exploded" in failures["bp_import"].error
    for name in PLUGINS:
        assert name in reg.retargeters, f"{name} was not loaded next to the broken plugin"
    builtins = [n for n, e in reg.retargeters.items() if e.plugin.builtin]
    assert builtins, "the built-in retargeters must still load"


def test_list_goes_on_and_names_the_broken_plugin(reg, capsys):
    count(AREA)
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    for name in PLUGINS:
        assert name in out
    failed = out.split("plugins that failed to load:")[1]
    assert named(failed, "bp_import") and "import exploded" in failed
    assert cli.main(["list", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert {"plugin": "bp_import", "distribution": DIST} == {k: data["failed_plugins"][0][k] for k in ("plugin", "distribution")}


def test_compare_goes_on_and_names_each_failure(reg, case):
    from faceretarget.evaluation import compare

    result = compare([case], methods=list(PLUGINS), registry=reg, metrics=["vertex_error_mean"])
    runs = {r.method: r for r in result.runs}
    count(AREA, len(runs))
    assert runs["bp_good"].status == "ok"
    for name in BAD:
        run = runs[name]
        assert run.status == "error", f"{name}: {run.status} {run.reason}"
        assert named(run.reason, name), f"{name}: the reason must name the plugin and its distribution: {run.reason}"
    assert runs["bp_vertices"].error["type"] == "PluginOutputError" and runs["bp_nan"].error["type"] == "PluginOutputError"


@pytest.fixture
def bundles(case, tmp_path):
    src, tgt = tmp_path / "source.npz", tmp_path / "target.npz"
    fr.io.save_bundle(case.source, src)
    fr.io.save_bundle(case.target, tgt)
    return src, tgt


@pytest.mark.parametrize("name", BAD)
def test_run_refuses_to_write_a_broken_result(name, reg, bundles, tmp_path, capsys):
    src, tgt = bundles
    out = tmp_path / "out.npz"
    count(AREA)
    code = cli.main(["run", name, "--source", str(src), "--target", str(tgt), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == cli.EXIT_ERROR, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert named(err, name), f"the error must name the plugin and its distribution: {err}"
    assert not out.exists(), "nothing may be written for a failed or invalid result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["source.npz", "target.npz"]


def test_run_good_plugin_writes(reg, bundles, tmp_path, capsys):
    src, tgt = bundles
    out = tmp_path / "out.npz"
    assert cli.main(["run", "bp_good", "--source", str(src), "--target", str(tgt), "--out", str(out)]) == 0, capsys.readouterr().err
    assert np.asarray(fr.load(out, kind="animation").vertices).shape[0] == 4


def test_batch_goes_on_and_names_each_failure(reg, bundles, tmp_path):
    from faceretarget.evaluation.batch import run_batch

    src, tgt = bundles
    jobs = [f'[[job]]\nshot = "{src.name}"\ncharacter = "{tgt.name}"\nmethod = "{n}"\nout = "out/{n}.npz"\n' for n in ["bp_good"] + BAD]
    manifest = tmp_path / "shots.toml"
    (tmp_path / "out").mkdir()
    manifest.write_text("\n".join(jobs))
    summary = run_batch(manifest, workers=1, registry=reg, progress=False)
    results = {r.name: r for r in summary.results}
    count(AREA, len(results))
    assert results["out/bp_good.npz"].status == "done"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["bp_good.npz"], "failed jobs must write nothing"
    for name in BAD:
        r = results[f"out/{name}.npz"]
        assert r.status == "failed"
        assert named(r.error, name), f"batch must name the plugin and its distribution: {r.error}"
