"""Policies that drive a backend in closed loop: observation -> action (see policies/base.py)."""
