"""The vLLM path: infer.py --endpoint and labrobfail-evaluate endpoint= against a loopback OpenAI-compatible
server (tests/fake_openai.py, backed by the same tiny model) give FailureAnalyzer's answers; requests carry the
image first, the same image for every question of a grid, and closed sets as structured-output choices."""

import json
import os

import pytest
from conftest import program, run, run_here
from fake_openai import FakeOpenAI
from serve_fixtures import TASKS, grids, mixed_model  # noqa: F401  (fixtures)
from test_train import small_ds  # noqa: F401  (session fixture)

KEY = "sk-test-" + "y" * 24


@pytest.fixture(scope="module")
def local(mixed_model):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer

    return FailureAnalyzer.from_pretrained(mixed_model)


@pytest.fixture(scope="module")
def fake(mixed_model):  # noqa: F811
    from labrobfail_vlm.analyzer import FailureAnalyzer

    f = FakeOpenAI(FailureAnalyzer.from_pretrained(mixed_model), api_key=KEY)
    os.environ["_FAKE_KEY"] = KEY
    yield f
    f.close()


def test_endpoint_answers_equal_the_local_model(fake, local, grids):  # noqa: F811
    from labrobfail_vlm import questions as Q
    from labrobfail_vlm.endpoint import ACTIONS_REGEX, EndpointAnalyzer

    ep = EndpointAnalyzer(fake.url, api_key_env="_FAKE_KEY")
    assert ep.client.model == fake.name  # the only model the server lists
    fake.requests.clear()
    got = ep.answers_batch(grids[:6], [TASKS[i % 3] for i in range(6)], [8] * 6, max_batch=3)
    want = local.answers_batch(grids[:6], [TASKS[i % 3] for i in range(6)], [8] * 6)
    assert {a["Q2"] for a in want} == {"Yes", "No"}
    for g, w in zip(got, want):
        assert {d: g[d] for d in ("Q1", "Q2", "Q3", "Q4", "Q5")} == {d: w[d] for d in ("Q1", "Q2", "Q3", "Q4", "Q5")}
        if w["Q2"] == "No":
            assert g["Q6"] == w["Q6"] == Q.NO_CORRECTION
        else:
            assert g["Q6"] and g["Q6"] != Q.NO_CORRECTION
    # requests: image first, one image per grid for all its questions, closed sets as structured outputs
    by_image: dict[str, list[dict]] = {}
    for body in fake.requests:
        img, text = body["messages"][0]["content"]
        assert img["type"] == "image_url" and text["type"] == "text" and body["temperature"] == 0.0
        by_image.setdefault(img["image_url"]["url"], []).append(body)
    assert len(by_image) == 6
    for bodies in by_image.values():
        texts = [b["messages"][0]["content"][1]["text"] for b in bodies]
        assert len({t.split(" Task: ")[0] for t in texts}) == 1  # the same preamble after the image: prefix cache
        so = [b.get("structured_outputs") for b in bodies]
        assert so[0] == {"regex": ACTIONS_REGEX} and so[1] == {"choice": ["Yes", "No"]}
        assert len(bodies) in (2, 6)  # after "No", Q3-Q6 are not asked
        if len(bodies) == 6:
            assert so[2] == {"choice": [str(i) for i in range(1, 9)]} and so[5] is None  # Q6 free text


def test_endpoint_template_mode_uses_choices(fake, local, grids):  # noqa: F811
    from labrobfail_vlm.endpoint import EndpointAnalyzer

    ep = EndpointAnalyzer(fake.url, fake.name, api_key_env="_FAKE_KEY", q6_mode="template")
    local.q6_mode = "template"
    objs = ["small beaker", "target area"]
    for g in grids[:2]:
        remote = json.loads(ep.analyze(g, "pick up the small beaker", objects=objs).to_json())
        here = json.loads(local.analyze(g, "pick up the small beaker", objects=objs).to_json())
        # an endpoint returns replies, not scores: no P(failure) through it
        assert remote.pop("p_failure") is None and 0.0 <= here.pop("p_failure") <= 1.0
        assert remote == here
    local.q6_mode = "free"


def _run(*args, env=None, here=False):
    """A console script or root script with `env` added, as a process (or in this one: here=True)."""
    if here:
        return run_here([*program(args[0]), *args[1:]], env=env)
    return run([*program(args[0]), *args[1:]], env={**os.environ, **(env or {})})


def test_infer_through_the_endpoint(fake, local, grids, tmp_path):  # noqa: F811
    grids[0].save(tmp_path / "g.png")
    r = _run(
        "infer.py",
        "--grid",
        str(tmp_path / "g.png"),
        "--task",
        "pick up the small beaker",
        "--endpoint",
        fake.url,
        "--num-frames",
        "8",
        env={"OPENAI_API_KEY": KEY},
    )
    assert r.returncode == 0, r.stderr[-2000:]
    got = json.loads(r.stdout)
    want = json.loads(local.analyze(grids[0], "pick up the small beaker", frames=8).to_json())
    assert got["failure"] is want["failure"] is True
    assert {k: got[k] for k in ("actions", "failure_frame", "severity", "category")} == {
        k: want[k] for k in ("actions", "failure_frame", "severity", "category")
    }
    for args, needle in (
        ([], "HTTPError"),  # no key: the server says 401
        (["--endpoint-model", "other"], "HTTPError: HTTP Error 404"),
        (["--model", "x"], "not both"),
    ):
        r = _run(
            "infer.py",
            "--grid",
            str(tmp_path / "g.png"),
            "--endpoint",
            fake.url,
            *args,
            env={"OPENAI_API_KEY": KEY if args else ""},
            here=True,  # one-line errors: in this process (the call above ran infer.py as a process)
        )
        assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr, r.stderr[-1000:]
        assert KEY not in r.stderr
    r = _run("infer.py", "--grid", str(tmp_path / "g.png"), "--endpoint", "http://127.0.0.1:9/v1", here=True)
    assert r.returncode == 2 and "cannot list models" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_evaluate_through_the_endpoint_matches_the_local_model(fake, mixed_model, small_ds, tmp_path):  # noqa: F811
    common = [f"dataset_dir={small_ds}", "split=test", "progress=false", "baselines=[]", "q6_template=false"]
    r = _run(
        "labrobfail-evaluate",
        f"endpoint={fake.url}",
        "endpoint_key_env=_FAKE_KEY",
        f"out_dir={tmp_path / 'e'}",
        "batch_size=3",
        *common,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    r = _run(
        "labrobfail-evaluate", f"model={mixed_model}", f"out_dir={tmp_path / 'm'}", "batch_size=4", *common, here=True
    )
    assert r.returncode == 0, r.stderr[-2000:]
    preds = [
        dict(
            (json.loads(line)["id"], json.loads(line)["prediction"])
            for line in (tmp_path / d / "predictions.jsonl").read_text().splitlines()
        )
        for d in ("e", "m")
    ]
    assert preds[0].keys() == preds[1].keys()
    assert {k: v for k, v in preds[0].items() if not k.endswith("_Q6")} == {
        k: v for k, v in preds[1].items() if not k.endswith("_Q6")
    }
    res = json.loads((tmp_path / "e" / "results.json").read_text())
    assert res["method"] == f"LabRobFail-VLM endpoint ({fake.name})"
    r = _run(
        "labrobfail-evaluate", f"endpoint={fake.url}", f"model={mixed_model}", f"dataset_dir={small_ds}", here=True
    )
    assert r.returncode == 2 and "exactly one" in r.stderr


def test_evaluate_batch_size_gives_the_same_predictions(mixed_model, small_ds, tmp_path):  # noqa: F811
    common = [f"model={mixed_model}", f"dataset_dir={small_ds}", "split=test", "progress=false", "baselines=[blind]"]
    outs, probs = [], []
    # batches of 1 and 5 with the tower's outputs cached across the bench's passes (the default), and 5 without
    for b, mb in ((1, 1024), (5, 1024), (5, 0)):
        out = tmp_path / f"{b}_{mb}"
        r = _run("labrobfail-evaluate", f"out_dir={out}", f"batch_size={b}", f"tower_cache_mb={mb}", *common, here=True)
        assert r.returncode == 0, r.stderr[-2000:]
        lines = [json.loads(x) for x in (out / "predictions.jsonl").read_text().splitlines()]
        probs.append([x.pop("p_failure", None) for x in lines])  # float sums over padded rows: equal to rounding
        outs.append(json.dumps(lines))
        res = json.loads((out / "results.json").read_text())
        outs.append(json.dumps({k: res["baselines"][k]["q2"] for k in res["baselines"]}))
    assert outs[0] == outs[2] == outs[4] and outs[1] == outs[3] == outs[5]
    assert [p is None for p in probs[0]] == [p is None for p in probs[1]] and any(p is not None for p in probs[0])
    for other in probs[1:]:
        assert [p or 0 for p in probs[0]] == pytest.approx([p or 0 for p in other], abs=1e-4)
    for bad in ("batch_size=0", "tower_cache_mb=lots"):
        r = _run("labrobfail-evaluate", bad, *common, here=True)
        assert r.returncode == 2 and bad.split("=")[0] in r.stderr


@pytest.mark.parametrize(
    "canned, needle",
    [
        ({"choice": "zzz"}, "reply to Q2 is neither Yes nor No: 'zzz'"),  # read as "no failure" before
        ({"choice": None}, "content is NoneType, not text"),  # was the text "None"
        ({"regex": ["run"]}, "content is list, not text"),
    ],
)
def test_unreadable_replies_are_one_line_errors(fake, grids, tmp_path, canned, needle):  # noqa: F811
    from labrobfail_vlm.endpoint import EndpointAnalyzer, EndpointError

    ep = EndpointAnalyzer(fake.url, fake.name, api_key_env="_FAKE_KEY")
    fake.canned = canned
    try:
        with pytest.raises(EndpointError, match=needle.replace("(", r"\(")):
            ep.answers(grids[0], "pick up the small beaker")
        grids[0].save(tmp_path / "g.png")
        argv = ["infer.py", "--grid", str(tmp_path / "g.png"), "--endpoint", fake.url, "--endpoint-model", fake.name]
        r = _run(*argv, env={"OPENAI_API_KEY": KEY}, here=True)
        assert r.returncode == 2 and needle in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert r.stdout == ""
    finally:
        fake.canned = {}


def test_a_redirecting_endpoint_gets_no_key_and_no_follow(monkeypatch):
    """An endpoint that answers 302 is refused: the key (and the grid) never reach the host it points to."""
    import threading
    import urllib.error
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    from labrobfail_vlm.llm_client import ChatClient

    seen: list[dict[str, str]] = []

    class Elsewhere(BaseHTTPRequestHandler):
        def log_message(self, *_):
            pass

        def do_GET(self):  # noqa: N802
            seen.append(dict(self.headers))
            body = json.dumps({"data": [{"id": "m"}]}).encode()
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

    other = ThreadingHTTPServer(("127.0.0.1", 0), Elsewhere)

    class Redirect(BaseHTTPRequestHandler):
        def log_message(self, *_):
            pass

        def do_GET(self):  # noqa: N802
            self.send_response(302)
            self.send_header("Location", f"http://127.0.0.1:{other.server_address[1]}/v1/models")
            self.send_header("Content-Length", "0")
            self.end_headers()

    first = ThreadingHTTPServer(("127.0.0.1", 0), Redirect)
    for srv in (first, other):
        threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        monkeypatch.setenv("_REDIRECT_KEY", KEY)
        client = ChatClient(f"http://127.0.0.1:{first.server_address[1]}/v1", "m", "_REDIRECT_KEY", 5)
        with pytest.raises(urllib.error.HTTPError) as err:
            client.models()
        assert err.value.code == 302 and seen == []
        assert ChatClient(f"http://127.0.0.1:{other.server_address[1]}/v1", "m", "_REDIRECT_KEY", 5).models() == ["m"]
        assert seen and seen[0]["Authorization"] == f"Bearer {KEY}"  # the direct call does carry it
    finally:
        for srv in (first, other):
            srv.shutdown()
            srv.server_close()
