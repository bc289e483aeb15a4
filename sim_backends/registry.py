"""Name -> class registries for backends and task templates, in the style of
ManiSkill's `register_env`: a decorator stores a spec with JSON-serialisable
default kwargs, and `make_backend` finds the class by name, importing the
backend's module only when it is asked for (so ManiSkill/SAPIEN stay optional
for a PyBullet user and vice versa).
"""

from __future__ import annotations

import importlib
import inspect
import json
from dataclasses import dataclass, field
from typing import Any, Callable

# Backends whose module is imported on first use; the module registers itself.
_LAZY_BACKEND_MODULES: dict[str, str] = {
    "pybullet": "sim_backends.pybullet.backend",
    "maniskill": "sim_backends.maniskill.backend",
}


@dataclass(frozen=True)
class Spec:
    name: str
    cls: Any
    kwargs: dict[str, Any] = field(default_factory=dict)


BACKENDS: dict[str, Spec] = {}
# Task templates are keyed by (backend, name): a template builds a plan in its backend's own terms
# (PyBullet's `Plan`), so two backends may each have a "pick_place" that share nothing but the name.
TASK_TEMPLATES: dict[tuple[str, str], Spec] = {}


def _json_kwargs(kind: str, name: str, kwargs: dict[str, Any]) -> dict[str, Any]:
    """Default kwargs must survive a JSON round trip: they go into run records and worker processes."""
    try:
        json.dumps(kwargs)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{kind} {name!r}: default kwargs must be JSON-serialisable ({e})") from None
    return dict(kwargs)


def register_backend(name: str, **default_kwargs: Any) -> Callable:
    """Class decorator: make a `FailureSource` subclass selectable by `backend=name`, with JSON-serialisable
    default kwargs."""
    kwargs = _json_kwargs("backend", name, default_kwargs)

    def deco(cls: Any) -> Any:
        from sim_backends.source import FailureSource

        if not (inspect.isclass(cls) and issubclass(cls, FailureSource)):
            raise ValueError(f"backend {name!r}: {cls!r} is not a FailureSource subclass")
        if name in BACKENDS:
            raise ValueError(f"backend {name!r} is already registered")
        BACKENDS[name] = Spec(name, cls, kwargs)
        return cls

    return deco


def register_task(name: str, backend: str, **default_kwargs: Any) -> Callable:
    """Decorator for one backend's task template (keyframe program + success goals)."""
    kwargs = _json_kwargs("task template", name, default_kwargs)

    def deco(fn: Any) -> Any:
        if not callable(fn):
            raise ValueError(f"task template {name!r}: {fn!r} is not callable")
        if (backend, name) in TASK_TEMPLATES:
            raise ValueError(f"task template {name!r} is already registered for backend {backend!r}")
        TASK_TEMPLATES[(backend, name)] = Spec(name, fn, kwargs)
        return fn

    return deco


def task_templates(backend: str) -> dict[str, Spec]:
    """The task templates registered for one backend, by name."""
    return {n: s for (b, n), s in TASK_TEMPLATES.items() if b == backend}


def available_backends() -> list[str]:
    return sorted(set(_LAZY_BACKEND_MODULES) | set(BACKENDS))


def backend_spec(name: str) -> Spec:
    if name not in BACKENDS and name in _LAZY_BACKEND_MODULES:
        importlib.import_module(_LAZY_BACKEND_MODULES[name])
    if name not in BACKENDS:
        raise ValueError(f"backend: unknown backend {name!r}; available: {', '.join(available_backends())}")
    return BACKENDS[name]


# Constructor parameters every entry point sets itself (from its own image_size / cameras keys, or for the
# policy server's physics-only source): never part of a `backend_kwargs` section.
_GENERIC_PARAMS = {"self", "image_size", "cameras", "render"}


def backend_option_names(name: str) -> set[str]:
    """The keys a `backend_kwargs` section may hold for backend `name`: its constructor's own parameters."""
    return set(inspect.signature(backend_spec(name).cls.__init__).parameters) - _GENERIC_PARAMS


def backend_options(name: str, section: dict[str, Any]) -> dict[str, Any]:
    """A `backend_kwargs` section checked for backend `name`: each key must be an option of its constructor;
    the backend then checks and resolves the values (`FailureSource.prepare_kwargs`, which loads scene and
    object files). A bad one is a ConfigError "backend_kwargs.<key>: <problem>"."""
    from labrobfail_vlm.config import ConfigError

    takes = backend_option_names(name)
    try:
        for k in section:
            if k not in takes:
                raise ValueError(f"{k}: not an option of the {name} backend")
        return backend_spec(name).cls.prepare_kwargs(dict(section))
    except ValueError as e:
        raise ConfigError(f"backend_kwargs.{e}") from None


def make_backend(name: str, **kwargs: Any):
    spec = backend_spec(name)
    return spec.cls(**{**spec.kwargs, **kwargs})
