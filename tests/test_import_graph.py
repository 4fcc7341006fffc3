"""The shape of ``app/``: imports flow one way, with no circles, and no module grows too large.

Every ``import`` in ``app/`` counts, at module level, inside functions and under
``TYPE_CHECKING`` alike: an import hidden in a function is still an arrow.  Layers, lowest first
(a module may import its own layer and those below it, never one above):

``app.core`` < ``app.clock``, ``app.config``, ``app.log``, ``app.kit`` < ``app.db`` <
``app.jobs`` < ``app.services`` < ``app.viewer`` < ``app.api`` < ``app.main`` < ``app.cli``,
``app.__main__`` < ``app.testing`` (the test and benchmark harness: nothing else in ``app``
imports it).

No function body in ``app/`` is longer than :data:`MAX_FUNCTION_LINES` lines (its docstring
excluded); :data:`LONG_FUNCTIONS_ALLOWED`, the ones once tolerated while being split, is empty.

The core is numeric code only: besides the layers, it imports none of the standard library's
network, mail, TLS or signing modules (:data:`FORBIDDEN_IN_CORE`; they belong in ``app.kit``).
The core's own, stricter wall (no web or database library at all) is
``tests/core/test_import_wall.py``.  The harness ``app.testing`` imports neither a test framework
nor the test suite (:data:`FORBIDDEN_IN_HARNESS`): benchmarks run it without pytest.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

APP = Path(__file__).resolve().parent.parent / "app"

LAYERS: tuple[tuple[str, ...], ...] = (
    ("app.core",),
    ("app.clock", "app.config", "app.log", "app.kit"),
    ("app.db",),
    ("app.jobs",),
    ("app.services",),
    ("app.viewer",),
    ("app.api",),
    ("app.main",),
    ("app.cli", "app.__main__"),
    ("app.testing",),
)
"""Lowest first; a module may import from its own layer and the layers before it."""

MAX_MODULE_LINES = 600

MAX_FUNCTION_LINES = 80
"""Lines of a function's body, from its first statement after the docstring to its last."""

LONG_FUNCTIONS_ALLOWED: frozenset[str] = frozenset()
"""Functions over :data:`MAX_FUNCTION_LINES` still tolerated: none left (the last,
``map_evidence.map_test``, was split).  Never add a function to it; a name in it that is no
longer long fails the test, so the set cannot go stale."""

FORBIDDEN_IN_CORE = ("socket", "http", "smtplib", "urllib", "email", "ssl", "hmac")
"""Standard-library packages ``app.core`` must not import (sockets, HTTP, mail, TLS, signing)."""

FORBIDDEN_IN_HARNESS = ("pytest", "_pytest", "tests")
"""Packages ``app.testing`` must not import: the test framework and the test suite."""


def module_name(path: Path, root: Path) -> str:
    """The dotted name of the module at ``path`` (a package is named by its ``__init__``)."""
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def app_modules(root: Path) -> dict[str, Path]:
    """Every module under ``root`` by dotted name."""
    return {module_name(path, root): path for path in sorted(root.rglob("*.py"))}


def imported_app_modules(name: str, path: Path, known: set[str]) -> set[str]:
    """The modules of ``known`` that the module ``name`` at ``path`` imports, anywhere in it."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            candidates = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            # ``from app.services import auth`` depends on the module ``auth``; ``from
            # app.services.auth import Principal`` on ``auth`` too.
            candidates = [
                f"{source}.{alias.name}" if f"{source}.{alias.name}" in known else source
                for alias in node.names
            ]
        else:
            continue
        for candidate in candidates:
            # ``import app.db.models`` also runs ``app`` and ``app.db``: only the deepest counts.
            while candidate and candidate not in known:
                candidate = candidate.rpartition(".")[0]
            if candidate and candidate != name:
                found.add(candidate)
    return found


def import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the modules of ``app`` it imports."""
    modules = app_modules(root)
    known = set(modules)
    return {name: imported_app_modules(name, path, known) for name, path in modules.items()}


def forbidden_imports(root: Path, package: str, forbidden: tuple[str, ...]) -> list[str]:
    """Every import of a ``forbidden`` package under ``root/package``, as ``'module -> name'``."""
    found = []
    for path in sorted((root / package).rglob("*.py")):
        name = module_name(path, root)
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                imported = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                imported = [node.module]
            else:
                continue
            found.extend(
                f"{name} -> {module}" for module in imported if module.split(".")[0] in forbidden
            )
    return sorted(found)


def forbidden_core_imports(root: Path) -> list[str]:
    """Every import of :data:`FORBIDDEN_IN_CORE` under ``root/core``, as ``'module -> name'``."""
    return forbidden_imports(root, "core", FORBIDDEN_IN_CORE)


def body_length(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines of ``function``'s body, its docstring excluded (nested functions count in it)."""
    body = function.body
    first = body[0] if body else None
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
        body = body[1:] if isinstance(first.value.value, str) else body
    if not body:
        return 0
    return (body[-1].end_lineno or body[-1].lineno) - body[0].lineno + 1


def long_functions(root: Path) -> dict[str, int]:
    """Every function under ``root`` whose body is over :data:`MAX_FUNCTION_LINES`, by dotted name
    (``module.function``, ``module.Class.method``), with its body's length."""
    found: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{prefix}.{child.name}"
                if (length := body_length(child)) > MAX_FUNCTION_LINES:
                    found[name] = length
                visit(child, name)
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}.{child.name}")
            else:
                visit(child, prefix)

    for name, path in app_modules(root).items():
        visit(ast.parse(path.read_text(), filename=str(path)), name)
    return found


def layer_of(module: str) -> int:
    """The index in :data:`LAYERS` of ``module`` (``app`` itself is below everything)."""
    for index, prefixes in enumerate(LAYERS):
        if any(module == prefix or module.startswith(prefix + ".") for prefix in prefixes):
            return index
    if module == "app":
        return -1
    raise AssertionError(f"{module} belongs to no layer: add it to LAYERS")


def upward_arrows(graph: dict[str, set[str]]) -> list[str]:
    """Every import of a higher layer, as ``'a -> b'``."""
    return sorted(
        f"{source} -> {target}"
        for source, targets in graph.items()
        for target in targets
        if layer_of(target) > layer_of(source)
    )


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    lowlink: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = lowlink[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                lowlink[node] = min(lowlink[node], lowlink[target])
            elif target in on_stack:
                lowlink[node] = min(lowlink[node], index[target])
        if lowlink[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return components


def test_every_module_of_app_belongs_to_a_layer():
    for name in app_modules(APP):
        layer_of(name)


def test_no_import_goes_from_a_lower_layer_to_a_higher_one():
    assert upward_arrows(import_graph(APP)) == []


def test_the_import_graph_of_app_has_no_cycle():
    assert import_cycles(import_graph(APP)) == []


def test_the_core_imports_no_network_mail_or_signing_module():
    assert forbidden_core_imports(APP) == []


def test_the_harness_imports_no_test_framework_and_no_test_module():
    assert forbidden_imports(APP, "testing", FORBIDDEN_IN_HARNESS) == []


def test_no_module_of_app_is_longer_than_the_limit():
    too_long = {
        str(path.relative_to(APP.parent)): lines
        for path in sorted(APP.rglob("*.py"))
        if (lines := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert too_long == {}


def test_no_function_body_of_app_is_longer_than_the_limit():
    too_long = long_functions(APP)
    assert {
        name: lines for name, lines in too_long.items() if name not in LONG_FUNCTIONS_ALLOWED
    } == {}
    # a function split since must leave the allow-list, which only shrinks
    assert sorted(LONG_FUNCTIONS_ALLOWED - set(too_long)) == []


# The checks themselves must be able to fail: a tree with a cycle, upward arrows (from the core
# and from the kit), network, mail and signing imports in the core, and long functions.


@pytest.fixture
def broken_tree(tmp_path: Path) -> Path:
    root = tmp_path / "app"
    for package in ("", "core", "kit", "db", "api", "testing"):
        (root / package).mkdir(parents=True, exist_ok=True)
        (root / package / "__init__.py").write_text("")
    (root / "core" / "numbers.py").write_text("def f():\n    from app.db import models\n")
    (root / "db" / "models.py").write_text("from app.db.session import engine\n")
    (root / "db" / "session.py").write_text("from . import models\nengine = None\n")
    (root / "api" / "routes.py").write_text("import app.db.models\nfrom app.core import numbers\n")
    (root / "core" / "alerts.py").write_text(
        "import hmac\nimport http.client\n\n\ndef send():\n    import smtplib, socket\n"
        "    from urllib.parse import urlsplit\n    from email.message import EmailMessage\n"
        "    from ssl import create_default_context\n    from app.kit import net\n"
    )
    (root / "testing" / "service.py").write_text(
        "import pytest\n\n\ndef start():\n    from tests.helpers.environment import require\n"
    )
    (root / "kit" / "net.py").write_text(
        "from app.core import numbers\nfrom app.db import models\n"
    )

    def statements(indent: str) -> str:
        return "".join(f"{indent}x{line} = {line}\n" for line in range(MAX_FUNCTION_LINES))

    (root / "db" / "queries.py").write_text(
        'def short():\n    """A docstring does not count.\n\n    More.\n    """\n'
        f"{statements('    ')}"
        f"\n\nclass Store:\n    def long(self):\n{statements(' ' * 8)}        return 1\n"
        f"\n    async def nested(self):\n        def inner():\n{statements(' ' * 12)}"
        f"            return 2\n\n        return inner\n"
    )
    return root


def test_the_checks_find_an_upward_arrow_and_a_cycle(broken_tree: Path):
    graph = import_graph(broken_tree)
    assert graph["app.api.routes"] == {"app.db.models", "app.core.numbers"}
    assert upward_arrows(graph) == [
        "app.core.alerts -> app.kit.net",
        "app.core.numbers -> app.db.models",
        "app.kit.net -> app.db.models",
    ]
    assert import_cycles(graph) == [["app.db.models", "app.db.session"]]


def test_the_core_wall_finds_network_mail_and_signing_imports(broken_tree: Path):
    assert forbidden_core_imports(broken_tree) == [
        "app.core.alerts -> email.message",
        "app.core.alerts -> hmac",
        "app.core.alerts -> http.client",
        "app.core.alerts -> smtplib",
        "app.core.alerts -> socket",
        "app.core.alerts -> ssl",
        "app.core.alerts -> urllib.parse",
    ]


def test_the_harness_check_finds_test_framework_and_test_suite_imports(broken_tree: Path):
    assert forbidden_imports(broken_tree, "testing", FORBIDDEN_IN_HARNESS) == [
        "app.testing.service -> pytest",
        "app.testing.service -> tests.helpers.environment",
    ]


def test_the_length_check_finds_long_methods_and_nested_functions(broken_tree: Path):
    # 80 statements after a docstring are allowed; 81 lines are not, in a method or nested
    assert long_functions(broken_tree) == {
        "app.db.queries.Store.long": MAX_FUNCTION_LINES + 1,
        "app.db.queries.Store.nested": MAX_FUNCTION_LINES + 4,
        "app.db.queries.Store.nested.inner": MAX_FUNCTION_LINES + 1,
    }
