"""Closed-loop supervision: supervisors (none, oracle, vlm) watch a running policy and correct it."""
