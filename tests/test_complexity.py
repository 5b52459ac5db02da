"""The tick's physics and allocation stay readable: no function of hapticd.physics or
hapticd.allocation is above cyclomatic complexity 30, as radon measures it."""

from __future__ import annotations

from pathlib import Path

from radon.complexity import cc_visit

import hapticd

ROOT = Path(hapticd.__file__).parent
PACKAGES = ("physics", "allocation")
MOST = 30


def _blocks(path: Path) -> list[tuple[str, int]]:
    """Every function and method of ``path`` with its complexity (classes' methods by
    their qualified names)."""
    out = []
    for block in cc_visit(path.read_text()):
        methods = getattr(block, "methods", None)
        if methods is not None:  # a class: radon scores its methods one by one
            out += [(f"{block.name}.{m.name}", m.complexity) for m in methods]
        else:
            out.append((block.name, block.complexity))
    return out


def test_no_function_of_the_physics_or_allocation_is_above_the_limit():
    files = sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))
    assert any(p.name == "contact.py" for p in files)  # the stage modules are measured
    over = {
        f"{p.relative_to(ROOT)}:{name}": cc for p in files for name, cc in _blocks(p) if cc > MOST
    }
    assert not over, f"above cyclomatic complexity {MOST}: {over}"


def test_the_measure_sees_a_function_above_the_limit(tmp_path):
    """The check would catch one: a function of 31 branches scores above 30."""
    body = "".join(f"    if x == {i}:\n        return {i}\n" for i in range(31))
    path = tmp_path / "branchy.py"
    path.write_text(f"def branchy(x):\n{body}    return -1\n")
    assert _blocks(path) == [("branchy", 32)]
