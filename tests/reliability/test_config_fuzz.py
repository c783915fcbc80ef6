"""Malformed ``registry.toml`` text is a ConfigError, never another exception or a half-read catalogue.

Three pools: documents built from random TOML values (with the real keys at random
places), single-field mutations of a valid entry, and the shipped ``registry.toml`` cut
or with characters changed. A clean result must be a catalogue the registry and the CLI
can use as is (the invariants below).
"""

import json
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from reliability.fuzzkit import failed, fuzz, toml_document, toml_values, typed

import faceretarget as fr
from faceretarget import errors
from faceretarget.capabilities import RIG_PARTS, SOURCE_EXTRAS, SOURCE_KINDS
from faceretarget.registry import read_catalogue

AREA = "registry.toml"
ROOT = Path(__file__).resolve().parents[2]
KEYS = ["entry_point", "aliases", "paper", "summary", "capabilities", "parameters"]
CAP_KEYS = ["sources", "needs", "outputs", "stream", "edit", "same_topology"]


VALUES = toml_values(["markers", "mesh", "weights", "vertices", "blendshapes", "landmarks"])
CAPS = st.dictionaries(st.sampled_from(CAP_KEYS + ["x"]), VALUES, max_size=6)
PARAMS = st.dictionaries(
    st.text(max_size=4),
    st.one_of(VALUES, st.fixed_dictionaries({"doc": VALUES}, optional={"default": VALUES})),
    max_size=3,
)
ENTRY = st.dictionaries(
    st.sampled_from(KEYS + ["other"]),
    st.one_of(VALUES, CAPS, PARAMS),
    max_size=7,
)
VALID = {
    "entry_point": "ep",
    "aliases": ["a1"],
    "paper": "p",
    "summary": "s",
    "capabilities": {
        "sources": ["markers"],
        "needs": ["blendshapes", ["layers", "examples"]],
        "outputs": "weights",
        "stream": False,
        "edit": True,
        "same_topology": False,
    },
    "parameters": {"alpha": {"default": 0.1, "doc": "d"}},
}


@st.composite
def mutated_entry(draw):
    entry = json.loads(json.dumps(VALID))
    where = draw(
        st.sampled_from(
            KEYS
            + [f"capabilities.{k}" for k in CAP_KEYS]
            + ["parameters.alpha", "parameters.alpha.doc"]
        )
    )
    value = draw(VALUES)
    node, *rest = where.split(".")
    if not rest:
        entry[node] = value
    elif len(rest) == 1:
        entry[node][rest[0]] = value
    else:
        entry[node][rest[0]][rest[1]] = value
    if draw(st.booleans()):
        entry.pop(draw(st.sampled_from(KEYS)), None)
    return entry


def assert_usable(catalogue: dict):
    """What the registry and the CLI rely on in a catalogue that was accepted."""
    assert isinstance(catalogue, dict)
    for name, entry in catalogue.items():
        assert isinstance(name, str)
        for key in ("entry_point", "summary", "paper"):
            assert isinstance(entry[key], str), f"[{name}] {key} accepted as {entry[key]!r}"
        assert isinstance(entry["aliases"], list) and all(
            isinstance(a, str) for a in entry["aliases"]
        )
        for p, spec in entry["parameters"].items():
            assert isinstance(spec, dict) and isinstance(spec.get("doc"), str), (
                f"[{name}.parameters] {p} accepted as {spec!r}"
            )
        caps = entry["capabilities"]
        assert isinstance(caps, dict)
        for key in ("stream", "edit", "same_topology"):
            assert isinstance(caps.get(key, False), bool), (
                f"[{name}.capabilities] {key} accepted as {caps[key]!r}"
            )
        assert caps.get("outputs", "vertices") in ("weights", "vertices"), (
            f"[{name}] outputs accepted as {caps.get('outputs')!r}"
        )
        assert set(caps) <= set(CAP_KEYS), (
            f"[{name}.capabilities] unknown keys accepted: {set(caps) - set(CAP_KEYS)}"
        )
        built = fr.Capabilities.from_dict(caps)
        assert all(s in SOURCE_KINDS for s in built.sources), (
            f"[{name}] sources accepted as {caps.get('sources')!r}"
        )
        for need in built.needs:
            options = need if isinstance(need, tuple) else (need,)
            assert all(o in RIG_PARTS + SOURCE_EXTRAS for o in options), (
                f"[{name}] needs accepted as {caps.get('needs')!r}"
            )


def check(text):
    result = typed(AREA, read_catalogue, text)
    if failed(result):
        assert isinstance(result, errors.ConfigError), f"{type(result).__name__}: {result}"
        assert "registry.toml" in str(result), "the message names the file"
    else:
        assert_usable(result)
    return result


@given(
    doc=st.one_of(
        st.dictionaries(st.text(max_size=5), VALUES, max_size=3),
        st.fixed_dictionaries(
            {
                "retargeters": st.one_of(
                    VALUES,
                    st.dictionaries(
                        st.text(min_size=1, max_size=5), st.one_of(ENTRY, VALUES), max_size=3
                    ),
                )
            }
        ),
    )
)
@fuzz(60)
def test_random_documents(doc):
    check(toml_document(doc))


@given(entry=mutated_entry())
@fuzz(80)
def test_one_field_wrong(entry):
    check(toml_document({"retargeters": {"m": entry}}))


def test_valid_entry_is_read():
    result = check(toml_document({"retargeters": {"m": VALID}}))
    assert not failed(result) and result["m"]["capabilities"]["needs"] == [
        "blendshapes",
        ["layers", "examples"],
    ]


@given(data=st.data())
@fuzz(60)
def test_shipped_file_cut_or_changed(data):
    text = (ROOT / "registry.toml").read_text(encoding="utf-8")
    at = data.draw(st.integers(0, len(text)))
    how = data.draw(st.sampled_from(["cut", "replace", "insert"]))
    if how == "cut":
        text = text[:at]
    elif how == "replace":
        text = text[:at] + data.draw(st.text(min_size=1, max_size=3)) + text[at + 1 :]
    else:
        text = (
            text[:at]
            + data.draw(
                st.sampled_from(["[", "]", "=", '"', "\n[retargeters.x]\n", "{", "\x00", "\ufeff"])
            )
            + text[at:]
        )
    check(text)


@given(
    text=st.one_of(
        st.text(max_size=200),
        st.binary(max_size=200).map(lambda b: b.decode("latin-1")),
        st.binary(max_size=50),
        st.none().map(lambda _: 42),
    )
)
@fuzz(40)
def test_random_text_and_wrong_types(text):
    check(text)


# ---------------------------------------------------------------------------------------
# batch manifests: malformed ones are typed errors; accepted paths never leave the root
# ---------------------------------------------------------------------------------------
from faceretarget.evaluation.batch import CASE_PREFIX, load_manifest  # noqa: E402

MANIFEST_AREA = "batch manifests"
METHOD = sorted(fr.registry.registry().retargeters)[0]
PATHS = [
    "shot.npz",
    "rig.npz",
    "out/a.glb",
    "a.npz",
    "b.glb",
    "../escape.glb",
    "/etc/passwd",
    "sub/../../x.glb",
    "link/x.glb",
    "case:synthetic?n_frames=4",
    "case:no-such",
    "case:synthetic?x=",
    "",
    " ",
    "out/../b.glb",
]
JOB_KEYS = ["shot", "character", "landmarks", "method", "params", "out", "name"]
JOB_VALUES = st.one_of(
    st.sampled_from(PATHS + [METHOD, "no-such-method"]),
    toml_values(PATHS),
    st.just({}),
    st.just({"alpha": 0.1}),
)
JOBS = st.dictionaries(st.sampled_from(JOB_KEYS + ["other"]), JOB_VALUES, max_size=7)


@st.composite
def manifests(draw):
    doc = {}
    if draw(st.booleans()):
        doc["defaults"] = draw(st.one_of(JOBS, toml_values()))
    doc["job"] = draw(
        st.one_of(
            st.lists(JOBS, max_size=3),
            toml_values(),
            st.lists(
                st.fixed_dictionaries(
                    {
                        "shot": st.sampled_from(PATHS),
                        "character": st.sampled_from(PATHS),
                        "method": st.just(METHOD),
                        "out": st.sampled_from(PATHS),
                    }
                ),
                min_size=1,
                max_size=3,
            ),
        )
    )
    if draw(st.booleans()):
        doc[draw(st.sampled_from(["jobs", "other"]))] = draw(toml_values())
    return doc


@pytest.fixture(scope="module")
def manifest_root(tmp_path_factory):
    base = tmp_path_factory.mktemp("manifest")
    root = base / "project"
    (root / "out").mkdir(parents=True)
    (root / "sub").mkdir()
    (base / "outside").mkdir()
    (root / "link").symlink_to(base / "outside")  # a symlink leading out of the root
    for name in ("shot.npz", "rig.npz", "a.npz"):
        (root / name).write_bytes(b"placeholder")
    return root


def inside(root: Path, value) -> bool:
    return (
        value is None
        or str(value).startswith(CASE_PREFIX)
        or Path(value).resolve().is_relative_to(root.resolve())
    )


@given(doc=manifests(), raw=st.one_of(st.none(), st.binary(max_size=200)))
@fuzz(80)
def test_manifest_any_document(doc, raw, manifest_root):
    path = manifest_root / "shots.toml"
    if raw is None:
        path.write_text(toml_document(doc), encoding="utf-8")
    else:
        path.write_bytes(raw)
    jobs = typed(MANIFEST_AREA, load_manifest, path)
    if failed(jobs):
        assert isinstance(jobs, (errors.ConfigError, errors.UnknownNameError)), (
            f"{type(jobs).__name__}: {jobs}"
        )
        return
    assert jobs, "an accepted manifest has jobs"
    for job in jobs:
        for value in (job.shot, job.character, job.landmarks, job.out):
            assert inside(manifest_root, value), f"manifest path {value!r} escapes {manifest_root}"
        assert not str(job.out).startswith(CASE_PREFIX)


@pytest.mark.parametrize(
    "escape", ["../escape.glb", "/tmp/abs.glb", "sub/../../x.glb", "link/x.glb", "out/../../x.glb"]
)
@pytest.mark.parametrize("key", ["out", "shot", "character", "landmarks"])
def test_manifest_paths_cannot_leave_the_root(escape, key, manifest_root):
    job = {"shot": "shot.npz", "character": "rig.npz", "method": METHOD, "out": "out/ok.glb"}
    job[key] = escape
    path = manifest_root / "escape.toml"
    path.write_text(toml_document({"job": [job]}), encoding="utf-8")
    result = typed(MANIFEST_AREA, load_manifest, path)
    assert isinstance(result, errors.ConfigError), f"{key} = {escape!r} was accepted"
    assert "outside" in str(result)


def test_manifest_output_may_not_be_another_jobs_input(manifest_root):
    """``--redo`` would otherwise replace job 2's performance file with job 1's result."""
    path = manifest_root / "chain.toml"
    jobs = [
        {
            "shot": "shot.npz",
            "character": "rig.npz",
            "method": METHOD,
            "out": "a.npz",
            "name": "one",
        },
        {
            "shot": "a.npz",
            "character": "rig.npz",
            "method": METHOD,
            "out": "out/two.glb",
            "name": "two",
        },
    ]
    path.write_text(toml_document({"job": jobs}), encoding="utf-8")
    result = typed(MANIFEST_AREA, load_manifest, path)
    assert isinstance(result, errors.ConfigError), "a job's output is another job's input"
