"""Simulator backends of LabRobFail-Sim behind one `FailureSource` API (see docs/ARCHITECTURE.md)."""

from sim_backends.registry import available_backends, make_backend, register_backend, register_task

__all__ = ["available_backends", "make_backend", "register_backend", "register_task"]
