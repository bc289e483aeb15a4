"""json-numpy, the array encoding of OpenVLA's REST deploy server (the `json_numpy` package's format).

An ndarray travels as `{"__numpy__": base64 of its C-order bytes, "dtype": numpy descr (e.g. "<f4"),
"shape": [...]}`; the "encoded" request form wraps a whole json-numpy document in a JSON string.
"""

from __future__ import annotations

import base64
import json
from typing import Any

import numpy as np


def _default(obj: Any) -> Any:
    if isinstance(obj, (np.ndarray, np.generic)):
        a = np.asarray(obj, order="C")  # (ascontiguousarray would turn a 0-d array into 1-d)
        return {"__numpy__": base64.b64encode(a.tobytes()).decode("ascii"),
                "dtype": np.lib.format.dtype_to_descr(a.dtype), "shape": list(a.shape)}
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _hook(d: dict[str, Any]) -> Any:
    if "__numpy__" not in d:
        return d
    dtype = np.lib.format.descr_to_dtype(d["dtype"])
    if dtype.hasobject:  # never unpickle: object arrays are refused
        raise ValueError("json-numpy: object arrays are not accepted")
    arr = np.frombuffer(base64.b64decode(d["__numpy__"], validate=True), dtype)
    shape = tuple(d.get("shape") or ())
    return arr.reshape(shape) if shape else arr[0]


def dumps(obj: Any) -> str:
    return json.dumps(obj, default=_default)


def loads(text: str | bytes) -> Any:
    return json.loads(text, object_hook=_hook)
