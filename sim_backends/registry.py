"""Backends and task templates, registered in the project's one registry (labrobfail_vlm/registry.py) in the style
of ManiSkill's `register_env`: a decorator stores a spec with JSON-serialisable default kwargs, and `make_backend`
finds the class by name, importing the backend's module only when it is asked for (so ManiSkill/SAPIEN stay
optional for a PyBullet user and vice versa).
"""

from __future__ import annotations

import inspect
from typing import Any, Callable

from labrobfail_vlm.registry import Registry, Spec

__all__ = [
    "BACKENDS",
    "Spec",
    "available_backends",
    "backend_options",
    "backend_spec",
    "make_backend",
    "register_backend",
    "register_task",
    "task_templates",
]


def _is_source(cls: Any) -> bool:
    from sim_backends.source import FailureSource

    return inspect.isclass(cls) and issubclass(cls, FailureSource)


# Backends whose module is imported on first use; the module registers itself.
BACKENDS = Registry(
    "backend",
    lazy={"pybullet": "sim_backends.pybullet.backend", "maniskill": "sim_backends.maniskill.backend"},
    check=_is_source,
    expects="FailureSource subclass",
)
# Task templates, one registry per backend: a template builds a plan in its backend's own terms (PyBullet's
# `Plan`), so two backends may each have a "pick_place" that share nothing but the name.
_TASKS: dict[str, Registry] = {}


def register_backend(name: str, **default_kwargs: Any) -> Callable:
    """Class decorator: make a `FailureSource` subclass selectable by `backend=name`."""
    return BACKENDS.register(name, **default_kwargs)


def _tasks(backend: str) -> Registry:
    return _TASKS.setdefault(backend, Registry(f"task template of backend {backend!r}"))


def register_task(name: str, backend: str, **default_kwargs: Any) -> Callable:
    """Decorator for one backend's task template (keyframe program + success goals)."""
    return _tasks(backend).register(name, **default_kwargs)


def task_templates(backend: str) -> dict[str, Spec]:
    """The task templates registered for one backend, by name."""
    return dict(_tasks(backend).specs)


def available_backends() -> list[str]:
    return BACKENDS.names()


def backend_spec(name: str) -> Spec:
    return BACKENDS.spec(name)


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
    return BACKENDS.make(name, **kwargs)
