"""A loopback OpenAI-compatible chat server backed by a real (tiny) FailureAnalyzer, for the endpoint tests.

It speaks the part of the API the endpoint path uses, as vLLM does: GET /v1/models, POST /v1/chat/completions
with one user message (image_url data: URL + text), `structured_outputs.choice` (the reply is one of the
choices: ranked as the local decoder ranks them), `structured_outputs.regex` (only the Q1 action-list pattern:
decoded as a constrained action list) and plain free text; optional bearer key. Every request body is recorded.
"""

from __future__ import annotations

import base64
import io
import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from PIL import Image


class FakeOpenAI:
    def __init__(self, analyzer: Any, name: str = "labrobfail-tiny", api_key: str | None = None):
        from labrobfail_vlm.endpoint import ACTIONS_REGEX
        from labrobfail_vlm.train.data import messages

        self.fa, self.name, self.requests = analyzer, name, []
        # a broken model: the reply's content for every request of a kind ("choice", "regex" or "free")
        self.canned: dict[str, Any] = {}
        lock = threading.Lock()
        fake = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *_: Any) -> None:
                pass

            def _send(self, code: int, obj: Any) -> None:
                data = json.dumps(obj).encode()
                self.send_response(code)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def _authorized(self) -> bool:
                if api_key and self.headers.get("Authorization") != f"Bearer {api_key}":
                    self._send(401, {"error": {"message": "invalid api key", "type": "auth"}})
                    return False
                return True

            def do_GET(self) -> None:  # noqa: N802
                if not self._authorized():
                    return
                if self.path != "/v1/models":
                    return self._send(404, {"error": {"message": "not found"}})
                self._send(200, {"object": "list", "data": [{"id": fake.name, "object": "model"}]})

            def do_POST(self) -> None:  # noqa: N802
                if not self._authorized():
                    return
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                fake.requests.append(body)
                if body.get("model") != fake.name:
                    return self._send(404, {"error": {"message": f"model {body.get('model')!r} not found"}})
                (msg,) = body["messages"]
                img_part, text_part = msg["content"]
                data = img_part["image_url"]["url"].split(",", 1)[1]
                image = Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB")
                so = body.get("structured_outputs") or {}
                if "regex" in so and so["regex"] != ACTIONS_REGEX:
                    return self._send(400, {"error": {"message": "unsupported regex"}})
                fa = fake.fa
                prompt = fa.processor.apply_chat_template(
                    messages(text_part["text"]), tokenize=False, add_generation_prompt=True
                )
                with lock:
                    pre = fa.decoder.prefill(dict(fa.processor(text=[prompt], images=[image], return_tensors="pt")))
                    if "choice" in so:
                        # ranked as the local decoder ranks that list: Q6 strategies (sentences of unequal
                        # length) by mean log-likelihood per token, the one-token answers by their likelihood
                        per_token = len({len(fa.decoder.encode_ids(c)) for c in so["choice"]}) > 1
                        reply = fa.decoder.choose(pre, so["choice"], per_token)
                    elif "regex" in so:
                        reply = fa.decoder.actions(pre)
                    else:
                        fa.decoder.max_new_tokens = int(body.get("max_tokens", 96))
                        reply = fa.decoder.free_text(pre)
                kind = next((k for k in ("choice", "regex") if k in so), "free")
                if kind in fake.canned:
                    reply = fake.canned[kind]
                self._send(
                    200,
                    {
                        "id": "chatcmpl-fake",
                        "object": "chat.completion",
                        "model": fake.name,
                        "choices": [
                            {"index": 0, "finish_reason": "stop", "message": {"role": "assistant", "content": reply}}
                        ],
                    },
                )

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
