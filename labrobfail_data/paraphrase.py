"""Optional LLM paraphrase of questions (and Q6 answers) through an OpenAI-compatible chat endpoint.

Off by default. The API key is read from the environment variable named in the config and
only ever placed in the Authorization header: never logged, never written. A reworded
record must pass the same rule-based filter as the original (labrobfail_data.annotate.check_record);
otherwise the original wording is kept and the rejection is counted.

Same seed, same data: each request carries a seed made from the build's seed and the record's id (servers that
honour it reply alike), and every reply is kept in the dataset folder (CACHE, keyed by the model and the request),
so a rebuild asks again only what it has not asked before.
"""

from __future__ import annotations

import copy
import hashlib
import json
import urllib.error
from pathlib import Path
from typing import Any

from labrobfail_vlm import questions as Q
from labrobfail_vlm.io import append_line
from labrobfail_vlm.llm_client import ChatClient

SYSTEM = (
    "You are an expert annotator for robotic manipulation tasks in chemical laboratory environments. "
    "Reword the given question (and the answer, when one is given) so that the meaning, every object name "
    'and every number stay exactly the same. Reply with JSON only: {"question": ..., "answer": ...}.'
)
CACHE = "paraphrase_cache.jsonl"  # in the dataset folder: {"key", "reply"} per line, appended as replies come


class Paraphraser:
    def __init__(self, base_url: str, model: str, api_key_env: str, timeout_s: float = 30.0, seed: int = 0):
        self.seed, self.cache_file, self.cache = int(seed), None, {}
        try:
            self.client = ChatClient(base_url, model, api_key_env, timeout_s)
        except ValueError as e:
            raise ValueError(f"paraphrase.{e}") from None
        try:  # an endpoint nobody answers at would reject every rewording silently: say so before the build
            self.client.models()
        except urllib.error.HTTPError:
            pass  # it answers (a server without GET /models is still a chat server)
        except (urllib.error.URLError, OSError) as e:
            why = getattr(e, "reason", None) or e
            raise ValueError(f"paraphrase.base_url: nothing answers at {self.client.base} ({why})") from None
        except (ValueError, KeyError, TypeError):
            pass  # it answers, in another format

    def open_cache(self, folder: Path) -> None:
        """Read the replies an earlier build of this folder kept (a torn last line is skipped) and keep new ones."""
        self.cache_file = Path(folder) / CACHE
        if self.cache_file.is_file():
            for line in self.cache_file.read_text(encoding="utf-8").splitlines():
                try:
                    row = json.loads(line)
                    self.cache[str(row["key"])] = str(row["reply"])
                except (ValueError, KeyError, TypeError):
                    continue

    def _chat(self, content: str, rid: str) -> dict[str, Any]:
        # one request per record, as without the cache: a question's few wordings must not share one rewording
        seed = int.from_bytes(hashlib.sha256(f"{self.seed}:{rid}".encode()).digest()[:4], "little")
        key = hashlib.sha256(json.dumps([self.client.model, SYSTEM, content, seed]).encode()).hexdigest()
        text = self.cache.get(key)
        if text is None:
            messages = [{"role": "system", "content": SYSTEM}, {"role": "user", "content": content}]
            text = self.client.chat(messages, temperature=0.7, seed=seed)
            self.cache[key] = text
            if self.cache_file is not None:  # a kill loses at most this reply
                append_line(self.cache_file, json.dumps({"key": key, "reply": text}))
        text = text.strip()
        if text.startswith("```"):
            text = text.strip("`").removeprefix("json").strip()
        out = json.loads(text)
        if not isinstance(out, dict):
            raise ValueError("reply is not a JSON object")
        return out

    def reword(self, rec: dict[str, Any], dim: str, task_name: str) -> dict[str, Any] | None:
        """A reworded copy of `rec`, or None when the endpoint fails or replies nonsense."""
        human, gpt = rec["conversations"]
        pre = "<image>\n" + Q.preamble(task_name) + " "
        if not human["value"].startswith(pre):
            return None
        rest = human["value"][len(pre) :]
        question, _, options = rest.partition("\nOptions:")
        payload = {"question": question} | ({"answer": gpt["value"]} if dim == "Q6" else {})
        try:
            out = self._chat(json.dumps(payload), str(rec["id"]))
        except (urllib.error.URLError, OSError, ValueError, KeyError, IndexError, TypeError):
            return None
        new_q = out.get("question")
        if not isinstance(new_q, str) or not new_q.strip() or "<image>" in new_q:
            return None
        new = copy.deepcopy(rec)
        new["conversations"][0]["value"] = pre + new_q.strip() + (f"\nOptions:{options}" if options else "")
        if dim == "Q6":
            ans = out.get("answer")
            if not isinstance(ans, str) or not ans.strip():
                return None
            new["conversations"][1]["value"] = ans.strip()
        return new
