"""Minimal client for OpenAI-compatible chat endpoints (GPT, Gemini's compatibility API, vLLM, ...).

The API key is read from the environment variable the caller names and only placed in the
Authorization header: never logged, never written, never part of an error message.
"""

from __future__ import annotations

import base64
import io
import json
import os
import urllib.request
from typing import Any


def image_data_url(image: Any) -> str:
    """A PIL image as a PNG data: URL (lossless, so the server sees the grid's exact pixels)."""
    buf = io.BytesIO()
    image.convert("RGB").save(buf, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


class NoRedirect(urllib.request.HTTPRedirectHandler):
    """An endpoint that answers 3xx is refused, not followed: urllib would resend every header but the content ones
    (the API key's Authorization with them) and the body (a grid, a robot's images) to the host it names."""

    def redirect_request(self, *args: Any, **kwargs: Any) -> None:
        return None  # urllib then raises HTTPError with the 3xx code


OPENER = urllib.request.build_opener(NoRedirect)


class ChatClient:
    def __init__(self, base_url: str, model: str, api_key_env: str = "OPENAI_API_KEY", timeout_s: float = 60.0):
        if not base_url.startswith(("http://", "https://")):
            raise ValueError(f"base_url: expected an http(s) URL, got {base_url!r}")
        self.base = base_url.rstrip("/")
        self.url = self.base + "/chat/completions"
        self.model, self.timeout = model, float(timeout_s)
        self._key = os.environ.get(api_key_env, "")

    def __repr__(self) -> str:  # never show the key
        return f"ChatClient({self.url!r}, model={self.model!r})"

    def _call(self, url: str, body: dict[str, Any] | None = None) -> Any:
        headers = {"Content-Type": "application/json"}
        if self._key:
            headers["Authorization"] = f"Bearer {self._key}"
        data = json.dumps(body).encode() if body is not None else None
        req = urllib.request.Request(url, data=data, method="POST" if body is not None else "GET", headers=headers)
        with OPENER.open(req, timeout=self.timeout) as r:  # scheme checked above; redirects refused (NoRedirect)
            return json.loads(r.read())

    def chat(
        self, messages: list[dict[str, Any]], temperature: float = 0.0, max_tokens: int = 256, **extra: Any
    ) -> str:
        """The reply text; `extra` goes into the request body as is (e.g. vLLM's `structured_outputs`).
        Raises OSError/ValueError/KeyError on transport or format problems."""
        reply = self._call(
            self.url,
            {"model": self.model, "temperature": temperature, "max_tokens": max_tokens, "messages": messages, **extra},
        )
        content = reply["choices"][0]["message"]["content"]
        if not isinstance(content, str):  # null (a refusal or tool call) or parts: not a reply this client reads
            raise ValueError(f"the reply's content is {type(content).__name__}, not text")
        return content

    def models(self) -> list[str]:
        """The model ids the server lists (GET /models)."""
        return [str(m["id"]) for m in self._call(self.base + "/models")["data"]]
