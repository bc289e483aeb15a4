"""Minimal client for OpenAI-compatible chat endpoints (GPT, Gemini's compatibility API, vLLM, ...).

The API key is read from the environment variable the caller names and only placed in the
Authorization header: never logged, never written, never part of an error message.
"""

from __future__ import annotations

import json
import os
import urllib.request
from typing import Any


class ChatClient:
    def __init__(self, base_url: str, model: str, api_key_env: str = "OPENAI_API_KEY", timeout_s: float = 60.0):
        if not base_url.startswith(("http://", "https://")):
            raise ValueError(f"base_url: expected an http(s) URL, got {base_url!r}")
        self.url = base_url.rstrip("/") + "/chat/completions"
        self.model, self.timeout = model, float(timeout_s)
        self._key = os.environ.get(api_key_env, "")

    def __repr__(self) -> str:  # never show the key
        return f"ChatClient({self.url!r}, model={self.model!r})"

    def chat(self, messages: list[dict[str, Any]], temperature: float = 0.0, max_tokens: int = 256) -> str:
        """The reply text; raises OSError/ValueError/KeyError on transport or format problems."""
        body = json.dumps({"model": self.model, "temperature": temperature, "max_tokens": max_tokens,
                           "messages": messages}).encode()
        headers = {"Content-Type": "application/json"}
        if self._key:
            headers["Authorization"] = f"Bearer {self._key}"
        req = urllib.request.Request(self.url, data=body, method="POST", headers=headers)
        with urllib.request.urlopen(req, timeout=self.timeout) as r:  # noqa: S310 - scheme checked above
            reply = json.loads(r.read())
        return str(reply["choices"][0]["message"]["content"])
