"""Name -> class registries for backends and task templates, in the style of
ManiSkill's `register_env`: a decorator stores a spec with JSON-serialisable
default kwargs, and `make_backend` finds the class by name, importing the
backend's module only when it is asked for (so ManiSkill/SAPIEN stay optional
for a PyBullet user and vice versa).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any, Callable

# Backends whose module is imported on first use; the module registers itself.
_LAZY_BACKEND_MODULES: dict[str, str] = {
    "pybullet": "sim_backends.pybullet.backend",
}


@dataclass(frozen=True)
class Spec:
    name: str
    cls: Any
    kwargs: dict[str, Any] = field(default_factory=dict)


BACKENDS: dict[str, Spec] = {}
TASK_TEMPLATES: dict[str, Spec] = {}


def _register(table: dict[str, Spec], kind: str, name: str, kwargs: dict[str, Any]) -> Callable:
    def deco(obj: Any) -> Any:
        if name in table:
            raise KeyError(f"{kind} {name!r} is already registered")
        table[name] = Spec(name, obj, dict(kwargs))
        return obj

    return deco


def register_backend(name: str, **default_kwargs: Any) -> Callable:
    """Class decorator: make a `FailureSource` implementation selectable by `backend=name`."""
    return _register(BACKENDS, "backend", name, default_kwargs)


def register_task(name: str, **default_kwargs: Any) -> Callable:
    """Decorator for a task template (keyframe generator + success predicate)."""
    return _register(TASK_TEMPLATES, "task template", name, default_kwargs)


def available_backends() -> list[str]:
    return sorted(set(_LAZY_BACKEND_MODULES) | set(BACKENDS))


def backend_spec(name: str) -> Spec:
    if name not in BACKENDS and name in _LAZY_BACKEND_MODULES:
        importlib.import_module(_LAZY_BACKEND_MODULES[name])
    if name not in BACKENDS:
        raise ValueError(f"backend: unknown backend {name!r}; available: {', '.join(available_backends())}")
    return BACKENDS[name]


def make_backend(name: str, **kwargs: Any):
    spec = backend_spec(name)
    return spec.cls(**{**spec.kwargs, **kwargs})
