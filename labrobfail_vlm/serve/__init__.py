"""LabRobFail-VLM as a network service: `POST /diagnose` (a grid or per-view keyframes -> Diagnosis JSON),
`GET /health`, `GET /info`.

    app.py      the FastAPI app factory: routes, the bearer-token and upload-size guard, one-line JSON errors
    batcher.py  the request queue: one model thread runs up to `max_batch` diagnoses per `analyze_batch` call
    form.py     request validation: multipart fields -> a DiagnosisRequest, or a 4xx with one line
    client.py   a standard-library client (robot stacks, tests, scripts/bench_serve.py)

The entry point is labrobfail-serve. FastAPI and uvicorn are imported only here, so the library itself does not
need them.
"""
