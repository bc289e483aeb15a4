"""The house stays small (the fast-loop issue's limits): no function over 100 lines and no class over 300 in the
source packages and scripts, so a change that grows one past its limit fails here rather than in a later review."""

import ast

from conftest import ROOT

SOURCE = ("labrobfail_vlm", "labrobfail_data", "sim_backends", "scripts")
LIMITS = {ast.FunctionDef: 100, ast.AsyncFunctionDef: 100, ast.ClassDef: 300}


def test_no_function_over_100_lines_and_no_class_over_300():
    over = []
    files = [f for d in SOURCE for f in sorted((ROOT / d).rglob("*.py"))]
    assert len(files) > 100  # the walk found the source
    for f in files:
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            limit = LIMITS.get(type(node))
            if limit is not None and node.end_lineno - node.lineno + 1 > limit:
                over.append(f"{f.relative_to(ROOT)}:{node.lineno} {node.name} {node.end_lineno - node.lineno + 1}")
    assert over == [], over
