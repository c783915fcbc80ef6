"""Benchmark of the studio's edit round trip (issue 19: under 100 ms at 1,500 frames).

A studio server on 127.0.0.1 (in this process, in a thread) holds the synthetic human case
at 1,500 frames and the weight-curve editing method's result; each timed call is one HTTP
request ``POST /api/edit`` (a new blendshape weight at one frame, propagated over the whole
shot by the method's own ``edit()``) up to the complete JSON answer with the new curves,
as the page makes it. Wall time, min and median of >= 5 repeats (one untimed call first);
the edit alone (``retargeter.edit`` on the same result, no HTTP) is timed in the same
process as the baseline. Every edit adds a constraint, as a user's edits do.

Run: ``python benchmarks/bench_studio.py [--quick] [--repeat N] [--json]``.
"""

from __future__ import annotations

import http.client
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C  # noqa: E402

N_FRAMES = 1500
CASE = f"synthetic-human?n_frames={N_FRAMES}&resolution=1000"
GOAL_S = 0.100


def main(argv=None) -> dict:
    args = C.parser(__doc__).parse_args(argv)
    n = C.repeats(args)
    result = {
        "script": "bench_studio",
        "machine": C.print_machine("bench_studio"),
        "rows": [],
        "scaling": [],
    }
    import tempfile

    from faceretarget.evaluation.harness import resolve_case
    from faceretarget.studio.server import StudioServer
    from faceretarget.studio.session import Session

    case = resolve_case(CASE)
    # the first method whose edit() takes new weights at a frame (as the page chooses it)
    with tempfile.TemporaryDirectory() as out:
        session = Session(case.source, case.target, truth=case.truth, name=case.name, out_dir=out)
        method = next(
            m["name"] for m in session.methods() if m["applies"] and "weights" in m["edit"]
        )
        server = StudioServer(session).start()
        try:
            conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=120)

            def post(path: str, body: dict) -> dict:
                data = json.dumps(body).encode()
                conn.request(
                    "POST",
                    path,
                    data,
                    {"X-Studio-Token": server.token, "Content-Type": "application/json"},
                )
                res = conn.getresponse()
                answer = json.loads(res.read())
                if res.status != 200:
                    raise SystemExit(f"bench_studio: {path} answered {res.status}: {answer}")
                return answer

            run = post("/api/run", {"method": method})
            name = run["weight_names"][0]
            calls = iter(range(10**6))

            def edit_request():
                i = next(calls)
                frame = 100 + (i * 37) % (N_FRAMES - 200)
                answer = post(
                    "/api/edit",
                    {
                        "id": run["id"],
                        "kind": "weights",
                        "frame": frame,
                        "weights": {name: 0.2 + 0.6 * (i % 2)},
                    },
                )
                assert answer["weights"] and answer["n_frames"] == N_FRAMES
                return answer

            t_http = C.timeit(edit_request, n)
            result_obj = session.result(run["id"])
            retargeter, animation = result_obj.retargeter, result_obj.animation
            t_edit = C.timeit(lambda: retargeter.edit(animation, frame=700, weights={name: 0.9}), n)
            conn.close()
        finally:
            server.stop()
    result["rows"].append(
        C.time_row(
            f"studio edit round trip, {N_FRAMES:,} frames ({method}, {len(run['weight_names'])} shapes): "
            "HTTP request to the JSON answer with the new curves",
            t_http,
            GOAL_S,
            baseline=(f"{method} edit() alone, no HTTP", t_edit),
            source="issue 19 item 3",
            note=f"load average before: {result['machine']['load_average'][0]:.2f}",
        )
    )
    C.print_rows(result["rows"])
    return C.finish(result, args)


if __name__ == "__main__":
    main()
