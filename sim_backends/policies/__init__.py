"""Policies that drive a backend in closed loop: observation -> action (see sim_backends/policies/base.py)."""
