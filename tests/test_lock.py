"""The dependency locks (requirements/) agree with pyproject.toml; the README installs from them."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest
from packaging.markers import default_environment
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
# A locked package: name==version, an optional marker, then its hashes on the next lines.
PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s;\\]+)\s*(?:;\s*([^\\]+?))?\s*\\?$")


def locked(path: Path) -> dict[str, list[tuple[str, str | None, bool]]]:
    """Each package of a lock: (version, marker or None, whether pyproject asks for it
    directly), one entry per marker branch."""
    out: dict[str, list[tuple[str, str | None, bool]]] = {}
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        m = PIN.match(line)
        if not m:
            continue
        # uv's annotation below the hashes names who asks for the package.
        j = i + 1
        while j < len(lines) and not PIN.match(lines[j]):
            j += 1
        notes = [ln for ln in lines[i + 1 : j] if ln.lstrip().startswith("#")]
        direct = any("pyproject.toml" in ln for ln in notes)
        name = canonicalize_name(m.group(1))
        out.setdefault(name, []).append((m.group(2), m.group(3), direct))
    return out


def wanted(extras: list[str]) -> list[Requirement]:
    """pyproject's requirements for an install with ``extras`` (and the build's)."""
    project = PYPROJECT["project"]
    reqs = [*project["dependencies"], *PYPROJECT["build-system"]["requires"]]
    for extra in extras:
        reqs += project["optional-dependencies"][extra]
    return [Requirement(r) for r in reqs]


def lock_disagreements(lock: dict, reqs: list[Requirement], env: dict[str, str]) -> list[str]:
    """What a lock and pyproject's requirements disagree on, in words; [] when they agree.
    Every requirement that applies to ``env`` is locked at a version it admits; every
    package the lock says pyproject asks for, it does ask for."""
    problems = []
    names = {canonicalize_name(r.name) for r in reqs}
    for req in reqs:
        if req.marker is not None and not req.marker.evaluate(env):
            continue
        name = canonicalize_name(req.name)
        pins = [v for v, marker, _ in lock.get(name, []) if marker is None or _applies(marker, env)]
        if not pins:
            problems.append(f"{req} is in pyproject.toml but not in the lock")
        elif not all(req.specifier.contains(v, prereleases=True) for v in pins):
            problems.append(f"{req} is in pyproject.toml but the lock pins {', '.join(pins)}")
    for name, entries in lock.items():
        if any(direct for *_, direct in entries) and name not in names:
            problems.append(
                f"the lock has {name} for hapticd, which pyproject.toml does not ask for"
            )
    return problems


def _applies(marker: str, env: dict[str, str]) -> bool:
    return Requirement(f"x; {marker}").marker.evaluate(env)  # type: ignore[union-attr]


@pytest.mark.parametrize(("lock_name", "extras"), [("run.txt", []), ("dev.txt", ["dev"])])
def test_the_lock_agrees_with_pyproject(lock_name, extras):
    lock = locked(ROOT / "requirements" / lock_name)
    problems = lock_disagreements(lock, wanted(extras), default_environment())
    assert problems == [], (
        f"requirements/{lock_name} and pyproject.toml disagree: {problems}; "
        "run `python scripts/lock.py` and commit requirements/"
    )


@pytest.mark.parametrize("lock_name", ["run.txt", "dev.txt"])
def test_every_locked_package_is_pinned_with_hashes_and_wheels_only(lock_name):
    text = (ROOT / "requirements" / lock_name).read_text()
    assert "--only-binary :all:" in text.splitlines()
    pins = [ln for ln in text.splitlines() if PIN.match(ln)]
    assert len(pins) > 10
    for line in pins:
        assert line.endswith("\\"), f"{line}: no hash follows"
    assert text.count("--hash=sha256:") >= len(pins)


def test_a_dependency_added_to_one_side_only_is_found():
    lock = locked(ROOT / "requirements" / "dev.txt")
    env = default_environment()
    reqs = wanted(["dev"])
    assert lock_disagreements(lock, reqs, env) == []
    # Added to pyproject, not locked.
    assert lock_disagreements(lock, [*reqs, Requirement("somethingnew>=1")], env) == [
        "somethingnew>=1 is in pyproject.toml but not in the lock"
    ]
    # A range the locked version falls outside.
    numpy = lock["numpy"][0][0]
    tight = [r for r in reqs if canonicalize_name(r.name) != "numpy"] + [
        Requirement(f"numpy>{numpy}")
    ]
    assert any("numpy" in p and "lock pins" in p for p in lock_disagreements(lock, tight, env))
    # Dropped from pyproject, still locked for hapticd.
    dropped = [r for r in reqs if canonicalize_name(r.name) != "trimesh"]
    assert lock_disagreements(lock, dropped, env) == [
        "the lock has trimesh for hapticd, which pyproject.toml does not ask for"
    ]


def test_the_readme_and_ci_install_from_the_locks():
    readme = (ROOT / "README.md").read_text()
    run_cmd = next(ln for ln in readme.splitlines() if "hapticd run configs/" in ln and "pip" in ln)
    test_cmd = next(ln for ln in readme.splitlines() if "python -m pytest" in ln and "pip" in ln)
    assert "-r requirements/run.txt" in run_cmd and "-r requirements/dev.txt" in test_cmd
    for cmd in (run_cmd, test_cmd):
        assert "--no-deps --no-build-isolation -e ." in cmd
    # uv comes from its own lock, with pip, before it installs the dev lock, hashes checked.
    assert test_cmd.index("pip install -r requirements/uv.txt") < test_cmd.index("uv pip install")
    assert "--require-hashes" in test_cmd
    ci = (ROOT / ".ci" / "run").read_text()
    assert "README.md" in ci  # CI runs the README's own line, not a copy of it


def test_the_uv_lock_is_the_dev_locks_pin_of_uv_with_its_hashes(tmp_path):
    """requirements/uv.txt, which pip installs first, is exactly the dev lock's uv entry
    (the same version and hashes): the dev lock is then installed by the uv it pins."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("lock_script", ROOT / "scripts" / "lock.py")
    script = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    spec.loader.exec_module(script)  # type: ignore[union-attr]

    def hashes(path: Path) -> set[str]:
        lines = path.read_text().splitlines()
        i = next(i for i, ln in enumerate(lines) if ln.startswith("uv=="))
        block = [lines[i]]
        for ln in lines[i + 1 :]:
            if not ln.startswith(" "):
                break
            block.append(ln)
        return {h for ln in block for h in re.findall(r"sha256:[0-9a-f]{64}", ln)}

    uv_lock, dev = ROOT / "requirements" / "uv.txt", ROOT / "requirements" / "dev.txt"
    assert locked(uv_lock).keys() == {"uv"}
    assert locked(uv_lock)["uv"][0][0] == locked(dev)["uv"][0][0]
    assert hashes(uv_lock) == hashes(dev) and len(hashes(dev)) > 1
    assert "--only-binary :all:" in uv_lock.read_text()
    # The lock script writes it from the dev lock, as it is; and tests a new lock with the
    # README's own command.
    script.write_bootstrap(dev, tmp_path / "uv.txt")
    assert (tmp_path / "uv.txt").read_text() == uv_lock.read_text()
    assert "requirements/uv.txt" in script.readme_test_command()
