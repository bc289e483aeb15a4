"""json-numpy, the wire format of OpenVLA's REST deploy server, behind the thin guard the project needs.

The encoding is the real `json_numpy` package's (the one OpenVLA's server and client use): an ndarray
travels as `{"__numpy__": base64 of its bytes, "dtype": numpy descr, "shape": [...]}`, and the "encoded"
request form wraps a whole json-numpy document in a JSON string. What the package does not do, and a
server or client facing a hostile peer must, is done here: a size limit, object arrays refused (their
dtype would ask numpy to read Python object pointers), and JSON nested too deeply turned from Python's
RecursionError into a clean error. Every refusal is a `WireError` with a one-line message.
"""

from __future__ import annotations

from typing import Any

import json_numpy
from numpy.lib.format import descr_to_dtype


class WireError(ValueError):
    """A payload that is not an acceptable json-numpy document; the message is one line."""


def one_line(e: BaseException, width: int = 80) -> str:
    """An exception as one short printable line: its text may come from the peer, and must neither spill over
    several log lines nor carry terminal control characters."""
    text = str(e).strip()
    line = text.splitlines()[0][:width] if text else ""
    return "".join(c if c.isprintable() else "?" for c in line) or type(e).__name__


def dumps(obj: Any) -> str:
    return json_numpy.dumps(obj)


def _refuse_object_arrays(d: dict[str, Any]) -> dict[str, Any]:
    """Runs before json-numpy's own hook on every JSON object: an array whose dtype holds Python objects is
    refused before numpy sees its bytes."""
    if "__numpy__" in d:
        try:
            dtype = descr_to_dtype(d.get("dtype"))
        except Exception as e:  # any malformed descr; numpy raises several types
            raise WireError(f"bad array dtype {str(d.get('dtype'))[:40]!r} ({one_line(e, 40)})") from None
        if dtype.hasobject:
            raise WireError("object arrays are refused")
    return d


def loads(data: str | bytes, max_bytes: int) -> Any:
    """Decode one json-numpy document of at most `max_bytes`; WireError for anything else."""
    if len(data) > max_bytes:
        raise WireError(f"payload of {len(data)} bytes is over the limit of {max_bytes}")
    try:
        return json_numpy.loads(data, object_hook=_refuse_object_arrays)
    except WireError:
        raise
    except RecursionError:
        raise WireError("JSON nested too deeply") from None
    except Exception as e:  # the decoder has no side effects: whatever it raises on hostile input means "invalid"
        raise WireError(one_line(e)) from None
