"""The layers stay layers: `shared/` packages import only lower layers (or themselves) and never the
services, benchmarks or tests above them, and the processes that never run the network do not import
torch or MuJoCo (ruff's banned-api rule checks the source; this checks what a process really loads,
transitive imports included)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO / "shared"
# Lower never imports higher; packages of one layer do not import each other.
LAYERS: dict[str, int] = {
    "vision": 0,
    "wire": 1,
    "model": 2,
    "transport": 2,
    "control": 2,
    "slam": 2,
    "sim": 2,
    "viz": 2,
    "perception": 3,
    "datasets": 3,
    "training": 4,
    "runtime": 4,
    "tools": 5,
}


# shared/ is the library beneath the services, benchmarks and tests: it imports none of them.
ABOVE_SHARED = ("services", "bench", "tests")
# The deliberate exceptions, each by file and module it loads, with why.
ALLOWED_UPWARD_IMPORTS: dict[tuple[str, str], str] = {
    ("shared/tools/settings_doc.py", "services.{}.settings"): (
        "`splittag settings` and docs/services.md print each service's settings class, which lives with its "
        "service; loaded by name (importlib) only when asked, so nothing in shared/ depends on services/ to import"
    ),
}


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) for every absolute import in a file, function-level ones included, and every module
    loaded by name (`importlib.import_module` / `__import__` with a literal or f-string: `{}` for each
    formatted part)."""
    out: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            names = [node.module] if node.module and node.level == 0 else []
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.Call) and node.args and _call_name(node.func) in ("import_module", "__import__"):
            names = [name] if (name := _literal_text(node.args[0])) is not None else []
        else:
            continue
        out.extend((node.lineno, name) for name in names)
    return out


def _call_name(func: ast.expr) -> str | None:
    return func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else None


def _literal_text(arg: ast.expr) -> str | None:
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    if isinstance(arg, ast.JoinedStr):
        return "".join(str(v.value) if isinstance(v, ast.Constant) else "{}" for v in arg.values)
    return None


def _shared_imports(path: Path) -> list[tuple[int, str]]:
    """(line, package) for every `shared.<package>` import in a file, function-level ones included."""
    out = []
    for line, name in _imports(path):
        parts = name.split(".")
        if parts[0] == "shared" and len(parts) > 1:
            out.append((line, parts[1]))
    return out


def test_every_shared_module_lives_in_a_layer() -> None:
    loose = [p.name for p in SHARED.glob("*.py") if p.name != "__init__.py"]
    assert not loose, f"modules outside the layer packages: {loose}"
    assert {p.name for p in SHARED.iterdir() if p.is_dir() and p.name != "__pycache__"} == set(LAYERS)


def test_lower_layers_never_import_higher_ones() -> None:
    bad = []
    for path in sorted(SHARED.rglob("*.py")):
        own = path.relative_to(SHARED).parts[0]
        if own not in LAYERS:
            continue
        for line, pkg in _shared_imports(path):
            if pkg == own:
                continue
            if pkg not in LAYERS or LAYERS[pkg] >= LAYERS[own]:
                bad.append(f"{path.relative_to(REPO)}:{line} ({own}, layer {LAYERS[own]}) imports shared.{pkg}")
    assert not bad, "\n".join(bad)


def test_shared_never_imports_services_bench_or_tests() -> None:
    """A module of shared/ importing a service, a benchmark or a test inverts the layers (and breaks the
    light install, which has no services/, bench/ or tests/). Only the named exceptions above."""
    bad, used = [], set()
    for path in sorted(SHARED.rglob("*.py")):
        where = path.relative_to(REPO).as_posix()
        for line, name in _imports(path):
            if name.split(".")[0] not in ABOVE_SHARED:
                continue
            if (where, name) in ALLOWED_UPWARD_IMPORTS:
                used.add((where, name))
            else:
                bad.append(f"{where}:{line} imports {name}")
    assert not bad, "\n".join(bad)
    assert used == set(ALLOWED_UPWARD_IMPORTS), f"exceptions no longer needed: {set(ALLOWED_UPWARD_IMPORTS) - used}"


@pytest.mark.parametrize("service", ["controller", "slam", "camera"])
def test_services_that_never_run_the_network_do_not_import_torch_or_mujoco(service: str) -> None:
    # What `python -m services.<name>` imports before it runs (its __main__ runs the service itself).
    code = (
        f"import sys, shared.runtime.service_main, services.{service}.settings, services.{service}.service; "
        "print(sorted(m for m in ('torch', 'mujoco') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", f"services.{service} imports {out.stdout.strip()}"
