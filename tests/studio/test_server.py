"""The studio's server as a client sees it: security (token, Host, Origin, files), bad
requests, a failing method, results, edits with undo and redo, exports, the Live Link Face
decoder and the live stream with a simulated sender, and the command line."""

from __future__ import annotations

import json
import os
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from studio_helpers import CASE, call

import faceretarget as fr
from faceretarget.errors import InputError
from faceretarget.studio import live as live_module

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Two files 'named on the command line', a file beside them that is not, a link out."""
    folder = tmp_path_factory.mktemp("inputs")
    named = folder / "named.json"
    named.write_text('{"jawOpen": 1}')
    other = folder / "secret.txt"
    other.write_text("not for the page")
    link = folder / "link.json"
    link.symlink_to(other)
    return named, other, link


@pytest.fixture(scope="module")
def server(boom_registry, case, inputs, start_studio):
    return start_studio(case, files=[inputs[0]])


@pytest.fixture(scope="module")
def spacetime(server):
    answer = call(server, "/api/run", method="POST", body={"method": "spacetime"})
    assert answer.status == 200, answer
    return answer.json()


def weights(summary) -> np.ndarray:
    import base64

    flat = np.frombuffer(base64.b64decode(summary["weights"]), dtype="<f4")
    return flat.reshape(summary["n_frames"], -1)


# -- security ---------------------------------------------------------------------------------
def test_served_on_loopback_with_a_long_random_token(server, start_studio, case):
    assert server.url.startswith(f"http://127.0.0.1:{server.port}/?token=")
    assert server.socket.getsockname()[0] == "127.0.0.1"
    assert len(server.token) >= 40
    assert start_studio(case).token != server.token


def test_the_token_is_required_everywhere_but_the_static_files(server):
    assert call(server, "/", token=None).status == 401
    assert call(server, "/", token="query").status == 200
    for path in ("/api/session", "/api/files", "/api/source?stop=1"):
        refused = call(server, path, token=None)
        assert refused.status == 401 and "token" in refused.json()["message"], path
        assert call(server, path, token="x" * len(server.token)).status == 401, path
        assert call(server, path, token=server.token[:-1]).status == 401, path
        assert call(server, path).status == 200, path
    assert call(server, "/static/app.js", token=None).status == 200


def test_changes_need_the_token_header_not_the_query(server):
    """A page of another site can put ?token= in a form's URL, never a custom header."""
    body = {"method": "spacetime"}
    answer = call(server, "/api/run", method="POST", body=body, token="query")
    assert answer.status == 401 and "X-Studio-Token header" in answer.json()["message"]
    assert call(server, "/api/run", method="POST", body=body, token="wrong").status == 401
    assert call(server, "/api/run", method="POST", body=body).status == 200


def test_the_token_is_compared_in_constant_time(server, monkeypatch):
    import secrets

    from faceretarget.studio import app

    seen, real = [], secrets.compare_digest

    def spy(a, b):
        seen.append((a, b))
        return real(a, b)

    monkeypatch.setattr(app.secrets, "compare_digest", spy)
    assert call(server, "/api/files").status == 200
    assert call(server, "/api/files", token="nope").status == 401
    assert seen[0] == (server.token.encode(), server.token.encode()) and len(seen) == 2


@pytest.mark.parametrize(
    "host",
    ["evil.example:{port}", "127.0.0.1:1", "127.0.0.2:{port}", "0.0.0.0:{port}", ""],
)
def test_other_hosts_are_refused(server, host):
    """DNS rebinding: a name that resolves to 127.0.0.1 still says its own name in Host."""
    answer = call(server, "/api/files", host=host.format(port=server.port) or " ")
    assert answer.status == 403 and "Host" in answer.json()["message"]


def test_other_origins_are_refused_and_the_own_accepted(server):
    for origin in ("http://evil.example", f"http://127.0.0.1:{server.port + 1}", "null"):
        answer = call(server, "/api/files", origin=origin)
        assert answer.status == 403 and "Origin" in answer.json()["message"], origin
        post = call(server, "/api/run", method="POST", body={"method": "spacetime"}, origin=origin)
        assert post.status == 403, origin
    for origin in (f"http://127.0.0.1:{server.port}", f"http://localhost:{server.port}"):
        assert call(server, "/api/files", origin=origin).status == 200
    assert call(server, "/api/files", host=f"localhost:{server.port}").status == 200


def test_only_the_named_files_are_readable(server, inputs):
    named, other, link = inputs
    listed = call(server, "/api/files").json()["files"]
    assert [f["path"] for f in listed] == [str(named)]
    got = call(server, f"/api/file?path={named}")
    assert got.status == 200 and got.body == named.read_bytes()
    spelled = f"{named.parent}/../{named.parent.name}/./{named.name}"  # the same file
    assert call(server, f"/api/file?path={spelled}").status == 200
    alias = named.parent.parent / f"{named.parent.name}-alias"  # a linked folder: the same file
    alias.symlink_to(named.parent, target_is_directory=True)
    assert call(server, f"/api/file?path={alias / named.name}").status == 200
    assert call(server, f"/api/file?path={alias / other.name}").status == 403
    for path in (other, link, "/etc/passwd", f"{named}/..", named.parent, "", "named.json"):
        answer = call(server, f"/api/file?path={path}")
        assert answer.status == 403, path
        assert "named on the command line" in answer.json()["message"]
    for path in ("/static/../cli.py", "/static/%2e%2e/cli.py", "/static/vendor/../../session.py"):
        assert call(server, path).status == 404, path


# -- requests -----------------------------------------------------------------------------------
def test_bad_requests_are_json_that_says_what_to_do(server, spacetime):
    rid = spacetime["id"]
    cases = [
        ("/api/run", None, b"not json", 400, "not JSON"),
        ("/api/run", None, b"[1, 2]", 400, "JSON object"),
        ("/api/run", {"method": "spacetim"}, None, 400, "did you mean 'spacetime'"),
        ("/api/run", {"method": "spacetime", "params": {"alpha": -1}}, None, 400, "alpha"),
        ("/api/run", {"method": "spacetime", "params": {"alhpa": 1}}, None, 400, "did you mean"),
        ("/api/run", {"method": "spacetime", "params": [1]}, None, 400, "params must be"),
        # checked against the manifest by the server, before the method runs (it would crash)
        ("/api/run", {"method": "studio_boom", "params": {"fail": "nope"}}, None, 400, "'crash'"),
        ("/api/edit", {"id": "nope", "kind": "weights"}, None, 404, "run a method first"),
        ("/api/edit", {"id": rid, "kind": "points", "frame": 3}, None, 400, "kind"),
        ("/api/edit", {"id": rid, "kind": "weights", "frame": 600}, None, 400, "frame"),
        (
            "/api/edit",
            {"id": rid, "kind": "weights", "frame": 3, "weights": {"jawOpn": 1}},
            None,
            400,
            "did you mean 'jawOpen'",
        ),
        (
            "/api/edit",
            {
                "id": rid,
                "kind": "weights",
                "frame": 3,
                "window": [10, 20],
                "weights": {"jawOpen": 1},
            },
            None,
            400,
            "outside the window",
        ),
        ("/api/undo", {"id": rid}, None, 400, "nothing to undo"),
        ("/api/export", {"id": rid, "format": "fbx"}, None, 400, "'glb'"),
    ]
    for path, body, raw, status, text in cases:
        answer = call(server, path, method="POST", body=body, raw=raw)
        assert answer.status == status, (path, body, answer)
        data = answer.json()
        assert text in data["message"] and data["error"], (path, body, data)
    for path, status in (
        ("/api/nothing", 404),
        ("/api/run", 405),
        ("/api/source?start=5&stop=2", 400),
        ("/api/source?start=x", 400),
        ("/api/result/vertices?id=nope", 404),
        ("/api/rig/nope", 404),
        ("/api/live", 409),
    ):
        answer = call(server, path)
        assert answer.status == status and answer.json()["message"], (path, answer)


def test_a_failing_method_is_reported_and_the_server_keeps_running(server):
    crash = call(server, "/api/run", method="POST", body={"method": "studio_boom"})
    assert crash.status == 500 and "kaboom" in crash.json()["message"]
    assert "keeps running" in crash.json()["message"]
    numerical = call(
        server,
        "/api/run",
        method="POST",
        body={"method": "studio_boom", "params": {"fail": "numerical"}},
    )
    assert numerical.status == 422 and "singular" in numerical.json()["message"]
    assert call(server, "/api/session").status == 200
    assert (
        call(server, "/api/run", method="POST", body={"method": "deformation_transfer"}).status
        == 200
    )


# -- what the page gets ----------------------------------------------------------------------------
def test_the_parameter_panel_comes_from_the_manifest(server, boom_registry):
    methods = {m["name"]: m for m in call(server, "/api/session").json()["methods"]}
    for name, m in methods.items():
        declared = boom_registry.resolve(name).parameters
        assert [p["name"] for p in m["parameters"]] == list(declared), name
        for p in m["parameters"]:
            assert p["doc"] == declared[p["name"]].doc and p["valid"] == declared[p["name"]].valid
    params = {p["name"]: p for p in methods["spacetime"]["parameters"]}
    assert params["alpha"] | {"doc": ""} == {
        "name": "alpha",
        "default": 0.01,
        "valid": "a finite number in [0, 1e12]",
        "doc": "",
        "nullable": False,
        "widget": "number",
        "min": 0.0,
        "max": 1e12,
        "step": "any",
    }
    assert params["mode"]["widget"] == "select" and "priorpf" in params["mode"]["choices"]
    assert params["scale_alpha"]["widget"] == "checkbox"
    assert params["constraints"]["widget"] == "json" and params["constraints"]["nullable"]
    assert methods["spacetime"]["edit"] == ["weights"] and methods["coating"]["edit"] == [
        "points",
        "detail",
    ]
    assert methods["layers"]["stream"] and methods["layers"]["edit"] == []


def test_results_are_cached_by_method_and_parameters(server, spacetime):
    again = call(server, "/api/run", method="POST", body={"method": "spacetime"}).json()
    assert again["cached"] and again["id"] == spacetime["id"]
    other = call(
        server, "/api/run", method="POST", body={"method": "spacetime", "params": {"alpha": 0.05}}
    ).json()
    assert (
        not other["cached"]
        and other["id"] != spacetime["id"]
        and other["params"] == {"alpha": 0.05}
    )


def test_weight_edit_propagates_in_its_window_and_undoes(server, case):
    run = call(
        server, "/api/run", method="POST", body={"method": "spacetime", "params": {"beta": 0.1}}
    ).json()
    original = weights(run)
    j = run["weight_names"].index("jawOpen")
    request = {"id": run["id"], "kind": "weights", "frame": 30, "window": [10, 50]}
    first = call(server, "/api/edit", method="POST", body=request | {"weights": {"jawOpen": 1.3}})
    assert first.status == 200, first
    edited = weights(first.json())
    assert edited[30, j] == pytest.approx(1.3, abs=1e-6)
    assert np.abs(edited[[25, 35], j] - original[[25, 35], j]).min() > 0.01  # propagated
    assert np.array_equal(edited[:10], original[:10]) and np.array_equal(edited[51:], original[51:])
    lo, hi = first.json()["changed"]
    assert 10 <= lo < 30 < hi <= 50
    assert first.json()["undo"] == 1 and first.json()["redo"] == 0
    second = call(
        server,
        "/api/edit",
        method="POST",
        body=request | {"frame": 40, "weights": {"jawOpen": 0.0}},
    )
    twice = weights(second.json())
    undone = call(server, "/api/undo", method="POST", body={"id": run["id"]}).json()
    assert np.array_equal(weights(undone), edited) and undone["redo"] == 1
    undone = call(server, "/api/undo", method="POST", body={"id": run["id"]}).json()
    assert np.array_equal(weights(undone), original) and undone["undo"] == 0
    redone = call(server, "/api/redo", method="POST", body={"id": run["id"]}).json()
    assert np.array_equal(weights(redone), edited)
    redone = call(server, "/api/redo", method="POST", body={"id": run["id"]}).json()
    assert np.array_equal(weights(redone), twice)
    assert call(server, "/api/redo", method="POST", body={"id": run["id"]}).status == 400
    call(server, "/api/undo", method="POST", body={"id": run["id"]})
    third = call(
        server, "/api/edit", method="POST", body=request | {"weights": {"jawOpen": 0.2}}
    ).json()
    assert third["redo"] == 0  # a new edit drops what could be redone
    back = call(server, "/api/undo", method="POST", body={"id": run["id"]}).json()
    assert np.array_equal(weights(back), edited)  # the step before the new edit


def test_point_and_detail_edits_go_through_the_method(server, case):
    run = call(server, "/api/run", method="POST", body={"method": "coating"}).json()
    assert run["outputs"] == "vertices" and run["edit"] == ["points", "detail"]
    rid, n_vertices = run["id"], run["n_vertices"]

    def vertices():
        data = call(server, f"/api/result/vertices?id={rid}").body
        return np.frombuffer(data, dtype="<f4").reshape(60, n_vertices, 3)

    before = vertices()
    goal = before[20, 100] + np.array([0.0, 0.6, 0.0])
    moved = call(
        server,
        "/api/edit",
        method="POST",
        body={
            "id": rid,
            "kind": "points",
            "frame": 20,
            "window": [10, 30],
            "vertex": 100,
            "position": goal.tolist(),
        },
    )
    assert moved.status == 200, moved
    after = vertices()
    assert np.linalg.norm(after[20, 100] - goal) < 0.5 * np.linalg.norm(before[20, 100] - goal)
    lo, hi = moved.json()["changed"]
    assert lo <= 20 <= hi
    shift = np.linalg.norm(after[:, 100] - before[:, 100], axis=1)
    assert shift.argmax() == 20  # (the bases change too: similar expressions elsewhere follow)
    radius = 0.1 * case.target.neutral.height
    removed = call(
        server,
        "/api/edit",
        method="POST",
        body={
            "id": rid,
            "kind": "detail",
            "frame": 20,
            "window": [12, 28],
            "vertex": 300,
            "radius": radius,
            "operation": "remove",
        },
    )
    assert removed.status == 200, removed
    detail = vertices()
    change = np.linalg.norm(detail[20] - after[20], axis=1)
    near = np.linalg.norm(after[20] - after[20, 300], axis=1) <= radius
    assert change[near].max() > 0 and change[~near].max() < change[near].max()
    undone = call(server, "/api/undo", method="POST", body={"id": rid})
    assert undone.status == 200 and np.array_equal(vertices(), after)


def test_the_error_heat_map_is_the_distance_to_the_truth(server, case):
    run = call(server, "/api/run", method="POST", body={"method": "deformation_transfer"}).json()
    data = call(server, f"/api/result/error?id={run['id']}&start=5&stop=7").body
    heat = np.frombuffer(data, dtype="<f4").reshape(2, -1)
    anim = fr.get("deformation_transfer").fit(case.source, case.target).retarget(case.source)
    expected = np.linalg.norm(anim.vertices[5:7] - case.truth.vertices[5:7], axis=2)
    np.testing.assert_allclose(
        heat, expected * 100 / case.meta["face_height"], rtol=1e-4, atol=1e-5
    )


def test_exports_are_new_files_that_read_back(server, spacetime, inputs):
    out = server.session.out_dir
    (out / "keep.txt").write_text("mine")
    paths = []
    for fmt in ("glb", "csv", "pc2", "glb"):
        answer = call(
            server, "/api/export", method="POST", body={"id": spacetime["id"], "format": fmt}
        )
        assert answer.status == 200, answer
        paths.append(Path(answer.json()["path"]))
    assert len(set(paths)) == 4 and all(p.parent == out.resolve() for p in paths)
    assert paths[0].name != paths[3].name and paths[3].suffix == ".glb"
    assert sorted(p.name for p in out.iterdir()) == sorted([*(p.name for p in paths), "keep.txt"])
    assert (out / "keep.txt").read_text() == "mine"
    glb = fr.load(paths[0], kind="animation")
    assert glb.n_frames == spacetime["n_frames"]
    csv = fr.load(paths[1], kind="weights")
    np.testing.assert_allclose(csv.weights, weights(spacetime), atol=1e-5)
    vertices = call(
        server, "/api/run", method="POST", body={"method": "deformation_transfer"}
    ).json()
    refused = call(
        server, "/api/export", method="POST", body={"id": vertices["id"], "format": "csv"}
    )
    assert refused.status == 409 and "export glb or pc2" in refused.json()["message"]


# -- live --------------------------------------------------------------------------------------------
def test_live_link_face_packets_round_trip_and_bad_ones_are_refused():
    values = np.linspace(-1, 1, 61)
    packet = live_module.decode(live_module.encode(values, frame=1234, subject="Jo"))
    assert packet.frame == 1234 and packet.subject == "Jo" and packet.rate == (60, 1)
    np.testing.assert_allclose(packet.values, values, atol=1e-6)
    by_hand = (  # the documented layout, written without the module's encoder
        struct.pack(">Bi", 6, 4)
        + b"dev1"
        + struct.pack(">i", 3)
        + b"Sam"
        + struct.pack(">ifiiB", 77, 0.5, 30, 1, 61)
        + struct.pack(">61f", *values)
    )
    read = live_module.decode(by_hand)
    assert (read.device_id, read.subject, read.frame, read.subframe) == ("dev1", "Sam", 77, 0.5)
    assert read.rate == (30, 1) and read.head[0] == pytest.approx(values[52], abs=1e-6)
    np.testing.assert_allclose(read.weights, values[:52], atol=1e-6)
    good = live_module.encode(values)
    assert good[0] == 6 and good[1:5] == (36).to_bytes(4, "big")  # version, device id length
    bad = {
        "version": bytes([5]) + good[1:],
        "ends inside": good[:-3],
        "length": good[:1] + (10**6).to_bytes(4, "big") + good[5:],
        "at most 61": good[: -4 * 61 - 1] + bytes([62]) + good[-4 * 61 :],
        "NaN": live_module.encode(np.full(61, np.nan)),
        "bytes": "text",
    }
    for text, data in bad.items():
        with pytest.raises(InputError, match=text):
            live_module.decode(data)


def test_live_stream_from_a_simulated_sender(boom_registry, case, start_studio):
    lines: list[str] = []
    server = start_studio(case, live=lines)
    link = server.session.live
    assert link.method == "layers"
    deadline = time.monotonic() + 60
    while link.status != "waiting":
        assert time.monotonic() < deadline and link.status != "failed", link.error
        time.sleep(0.05)
    frames = np.zeros((25, 61))
    frames[:, 17] = np.linspace(0, 1, 25)  # JawOpen
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(b"\x06garbage", ("127.0.0.1", link.port))
    while link.bad_packets == 0:  # refused, counted, and the stream goes on
        assert time.monotonic() < deadline, link.info()
        time.sleep(0.02)
    live_module.send(link.port, frames, fps=60)
    while link.frames + link.dropped < 25:
        assert time.monotonic() < deadline, link.info()
        time.sleep(0.02)
    info = link.info()
    assert info["bad_packets"] == 1 and info["frames"] >= 10
    assert (
        sum("ms (packet received to retargeted frame)" in line for line in lines) == info["frames"]
    )
    answer = call(server, "/api/live?after=0")
    got = answer.json()
    assert got["info"]["status"] == "streaming" and got["frame"]["seq"] == info["frames"]
    import base64

    target = np.frombuffer(base64.b64decode(got["frame"]["target"]), dtype="<f4").reshape(-1, 3)
    assert target.shape == (case.target.neutral.n_vertices, 3) and np.isfinite(target).all()
    opened = target - case.target.neutral.vertices
    assert np.abs(opened).max() > 1e-3 * case.target.neutral.height  # the jaw moved the face
    assert call(server, f"/api/live?after={info['frames']}").json()["frame"] is None


# -- the command line -----------------------------------------------------------------------------------
def test_command_prints_the_url_and_serves(tmp_path):
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "faceretarget.cli",
            "studio",
            CASE,
            "--out",
            str(tmp_path),
            "--method",
            "spacetime",
            "--set",
            "alpha=0.02",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    try:
        line = proc.stdout.readline()
        assert line.startswith("faceretarget studio: http://127.0.0.1:"), line
        url = line.split()[2]

        class Server:
            port = int(url.split(":")[2].split("/")[0])
            token = url.split("token=")[1]

        assert call(Server, "/", token="query").status == 200
        info = call(Server, "/api/session").json()
        assert info["default_method"] == "spacetime" and info["default_params"] == {"alpha": 0.02}
        assert info["truth"] and info["files"] == []
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_command_errors_are_one_line():
    for args, text in (
        ([], "give a CASE"),
        (["nocase"], "no case named 'nocase'"),
        ([CASE, "--method", "spacetime", "--set", "alpha=-1"], "alpha"),
        ([CASE, "--source", "x.c3d"], "not both"),
    ):
        out = subprocess.run(
            [sys.executable, "-m", "faceretarget.cli", "studio", *args],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert out.returncode == 2 and text in out.stderr, (args, out.stderr)
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr


def test_the_web_server_is_imported_only_by_the_studio():
    code = (
        "import sys, faceretarget, faceretarget.cli as c; c.build_parser(); c.main(['list']); "
        "import json; print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in ('starlette', 'uvicorn'))))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=60,
        env=dict(os.environ),
    )
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []
