"""A standard-library client for the diagnosis server (no extra dependency for a robot stack).

    from labrobfail_vlm.serve.client import DiagnosisClient
    c = DiagnosisClient("http://127.0.0.1:8100")          # token from $LABROBFAIL_API_TOKEN, if set
    diagnosis = c.diagnose(grid="grid.png", task="pick up the small beaker")
    diagnosis = c.diagnose(frames={"front": [f0, f1, ...], "side": [...]}, task="...", prefix=3)
    diagnosis = c.diagnose(videos={"front": "front.mp4", "side": "side.mp4"}, task="...", keyframes="motion")

One client holds one keep-alive connection: use one per thread. A reply other than 200 raises ServiceError
with the server's one-line message. `retries=N` sends a request again, up to N times `retry_wait_s` apart, when
the server cannot be reached or drops the connection before replying (a server restarting after a crash); a
diagnosis is a pure function of its request, so sending it twice is safe.
"""

from __future__ import annotations

import http.client
import io
import json
import os
import time
import uuid
from pathlib import Path
from typing import Any, Mapping, Sequence
from urllib.parse import urlsplit

Part = tuple[str, "str | tuple[str, bytes, str]"]  # (field, text) or (field, (filename, data, content type))


class ServiceError(RuntimeError):
    def __init__(self, status: int, message: str):
        super().__init__(f"{status}: {message}")
        self.status, self.message = status, message


def multipart(parts: Sequence[Part]) -> tuple[bytes, str]:
    """Encode form fields and files; returns (body, content type)."""
    boundary = uuid.uuid4().hex
    out = io.BytesIO()
    for name, value in parts:
        out.write(f"--{boundary}\r\n".encode())
        if isinstance(value, tuple):
            filename, data, ctype = value
            out.write(
                f'Content-Disposition: form-data; name="{name}"; filename="{filename}"\r\n'
                f"Content-Type: {ctype}\r\n\r\n".encode()
            )
            out.write(data)
        else:
            out.write(f'Content-Disposition: form-data; name="{name}"\r\n\r\n'.encode())
            out.write(str(value).encode())
        out.write(b"\r\n")
    out.write(f"--{boundary}--\r\n".encode())
    return out.getvalue(), f"multipart/form-data; boundary={boundary}"


def image_part(name: str, image: Any, filename: str = "image.png") -> Part:
    """A file part from a path, PNG/JPEG bytes, a PIL image or an HxWx3 uint8 array (sent as PNG)."""
    if isinstance(image, (str, Path)):
        p = Path(image)
        return name, (p.name, p.read_bytes(), "image/jpeg" if p.suffix.lower() in (".jpg", ".jpeg") else "image/png")
    if isinstance(image, (bytes, bytearray)):
        return name, (filename, bytes(image), "application/octet-stream")
    from PIL import Image

    img = image if isinstance(image, Image.Image) else Image.fromarray(image)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return name, (filename, buf.getvalue(), "image/png")


class DiagnosisClient:
    def __init__(
        self,
        url: str = "http://127.0.0.1:8100",
        token_env: str = "LABROBFAIL_API_TOKEN",
        timeout_s: float = 120.0,
        retries: int = 0,
        retry_wait_s: float = 1.0,
    ):
        u = urlsplit(url)
        if u.scheme not in ("http", "https") or not u.hostname:
            raise ValueError(f"url: expected http(s)://host:port, got {url!r}")
        self.scheme, self.host, self.port = u.scheme, u.hostname, u.port or (443 if u.scheme == "https" else 80)
        self.timeout = timeout_s
        self.retries, self.retry_wait_s = max(0, int(retries)), float(retry_wait_s)
        self._token = os.environ.get(token_env, "")
        self._conn: http.client.HTTPConnection | None = None

    def __repr__(self) -> str:  # never show the token
        return f"DiagnosisClient({self.scheme}://{self.host}:{self.port})"

    def request(
        self, method: str, path: str, body: bytes | None = None, headers: Mapping[str, str] | None = None
    ) -> tuple[int, Any]:
        """(status, decoded JSON body); reconnects once if a kept-alive connection was closed by the server, and
        retries `retries` times when the server is unreachable or drops the connection."""
        hdrs = {**({"Authorization": f"Bearer {self._token}"} if self._token else {}), **(headers or {})}
        for attempt in range(self.retries + 2):  # +1: a kept-alive connection the server closed costs one try
            if self._conn is None:
                cls = http.client.HTTPSConnection if self.scheme == "https" else http.client.HTTPConnection
                self._conn = cls(self.host, self.port, timeout=self.timeout)
            try:
                self._conn.request(method, path, body=body, headers=hdrs)
                r = self._conn.getresponse()
                data = r.read()
                break
            except (http.client.RemoteDisconnected, http.client.IncompleteRead, ConnectionError) as e:
                self.close()
                if attempt >= self.retries + (0 if isinstance(e, ConnectionRefusedError) else 1):
                    raise
                if attempt or isinstance(e, ConnectionRefusedError):
                    time.sleep(self.retry_wait_s)
        try:
            return r.status, json.loads(data) if data else None
        except ValueError:
            return r.status, {"error": data[:200].decode("utf-8", "replace")}

    def post_form(self, parts: Sequence[Part]) -> tuple[int, Any]:
        body, ctype = multipart(parts)
        return self.request("POST", "/diagnose", body, {"Content-Type": ctype})

    def diagnose(
        self,
        grid: Any = None,
        frames: Mapping[str, Sequence[Any]] | None = None,
        task: str = "",
        prefix: int | None = None,
        objects: Sequence[str] = (),
        videos: Mapping[str, str | Path | bytes] | None = None,
        keyframes: str | None = None,
    ) -> dict[str, Any]:
        """One of `grid`, `frames` (view -> keyframes) or `videos` (view -> a video file or its bytes; the server
        picks `keyframes`: uniform or motion)."""
        parts: list[Part] = []
        if grid is not None:
            parts.append(image_part("grid", grid))
        for view, imgs in (frames or {}).items():
            parts.extend(image_part(f"frames.{view}", im, f"{view}-{i}.png") for i, im in enumerate(imgs))
        for view, video in (videos or {}).items():
            data = video if isinstance(video, bytes) else Path(video).read_bytes()
            name = f"{view}.mp4" if isinstance(video, bytes) else Path(video).name
            parts.append((f"video.{view}", (name, data, "video/mp4")))
        if keyframes:
            parts.append(("keyframes", keyframes))
        if task:
            parts.append(("task", task))
        if prefix is not None:
            parts.append(("prefix", str(prefix)))
        if objects:
            parts.append(("objects", ",".join(objects)))
        return self._ok(*self.post_form(parts))

    def health(self) -> dict[str, Any]:
        return self._ok(*self.request("GET", "/health"))

    def info(self) -> dict[str, Any]:
        return self._ok(*self.request("GET", "/info"))

    @staticmethod
    def _ok(status: int, body: Any) -> Any:
        if status != 200:
            raise ServiceError(status, (body or {}).get("error", "") if isinstance(body, dict) else str(body))
        return body

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
