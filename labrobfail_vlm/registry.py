"""A small name -> factory registry with lazy module imports (policies, supervisors).

    POLICIES = Registry("policy", lazy={"act": "policies.act.policy"})

    @POLICIES.register("scripted")
    class ScriptedPolicy(Policy): ...

    POLICIES.make("act", checkpoint="runs/act/final")   # imports policies.act.policy on first use

Heavy optional dependencies (torch, transformers, a simulator) stay unimported until a user asks for
the entry that needs them, as in sim_backends/registry.py.
"""

from __future__ import annotations

import importlib
from typing import Any, Callable


class Registry:
    def __init__(self, kind: str, lazy: dict[str, str] | None = None):
        self.kind = kind
        self.lazy = dict(lazy or {})  # name -> module that registers it on import
        self.entries: dict[str, Callable[..., Any]] = {}

    def register(self, name: str) -> Callable:
        """Decorator for a class or factory function selectable by `name`."""
        def deco(obj: Any) -> Any:
            if not callable(obj):
                raise ValueError(f"{self.kind} {name!r}: {obj!r} is not callable")
            if name in self.entries and self.entries[name] is not obj:
                raise ValueError(f"{self.kind} {name!r} is already registered")
            self.entries[name] = obj
            return obj
        return deco

    def names(self) -> list[str]:
        return sorted(set(self.lazy) | set(self.entries))

    def get(self, name: str) -> Callable[..., Any]:
        if name not in self.entries and name in self.lazy:
            importlib.import_module(self.lazy[name])
        if name not in self.entries:
            raise ValueError(f"{self.kind}: unknown {self.kind} {name!r}; available: {', '.join(self.names())}")
        return self.entries[name]

    def make(self, name: str, **kwargs: Any) -> Any:
        return self.get(name)(**kwargs)
