"""The numeric core must not import the web, database, queue or settings layers."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[2] / "app" / "core"
FORBIDDEN_TOP_LEVEL = {
    "fastapi",
    "starlette",
    "sqlalchemy",
    "pydantic",
    "pydantic_settings",
    "huey",
    "viser",
    "uvicorn",
    "alembic",
}
FORBIDDEN_APP = {
    "app.api",
    "app.db",
    "app.services",
    "app.jobs",
    "app.viewer",
    "app.config",
    "app.cli",
    "app.main",
    "app.kit",
    "app.testing",
}


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def printed_by_a_fresh_process(code: str) -> str:
    """What ``code`` prints, run by a new Python process (its imports start from nothing)."""
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    return result.stdout.strip()


def test_core_sources_import_nothing_outside_the_core():
    offenders = []
    for path in sorted(CORE.rglob("*.py")):
        for module in imported_modules(path):
            top = module.split(".")[0]
            if top in FORBIDDEN_TOP_LEVEL or any(
                module == name or module.startswith(name + ".") for name in FORBIDDEN_APP
            ):
                offenders.append(f"{path.relative_to(CORE.parent.parent)} imports {module}")
    assert offenders == []


def test_importing_the_core_loads_no_web_or_database_module():
    code = (
        "import sys, app.core, app.core.cloud, app.core.errors\n"
        "import pkgutil, importlib\n"
        "for info in pkgutil.walk_packages(app.core.__path__, 'app.core.'):\n"
        "    importlib.import_module(info.name)\n"
        f"forbidden = {sorted(FORBIDDEN_TOP_LEVEL)!r}\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in forbidden)\n"
        "print(','.join(bad))\n"
    )
    assert printed_by_a_fresh_process(code) == ""


def test_reading_a_result_and_its_labels_loads_no_localiser():
    """The labels have one home (``app.core.labels``): a reader of results (the viewer, the
    harness's stand-in pipeline) needs no import of ``app.core.localise``."""
    code = (
        "import sys, app.core.labels, app.core.comparison.result\n"
        "print(','.join(sorted(m for m in sys.modules if m.startswith('app.core.localise'))))\n"
    )
    assert printed_by_a_fresh_process(code) == ""


LABEL_NAMES = {"LABEL_CHANGED", "LABEL_UNCHANGED", "LABEL_UNOBSERVED"}
REPOSITORY = CORE.parents[1]


def test_the_labels_are_defined_and_imported_in_one_place():
    """Every module takes the labels from ``app.core.labels``: none defines them again and no
    package re-exports them (``app.core.localise`` did, for the tiler alone)."""
    offenders = []
    for folder in ("app", "tests", "bench"):
        for path in sorted((REPOSITORY / folder).rglob("*.py")):
            text = path.read_text()
            if not any(name in text for name in LABEL_NAMES):
                continue  # parse only the files that name a label
            tree = ast.parse(text, filename=str(path))
            where = path.relative_to(REPOSITORY)
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom) and node.module != "app.core.labels":
                    taken = sorted(LABEL_NAMES & {alias.name for alias in node.names})
                    if taken:
                        offenders.append(f"{where} imports {taken} from {node.module}")
                elif isinstance(node, ast.Assign) and where != Path("app/core/labels.py"):
                    for target in node.targets:
                        if isinstance(target, ast.Name) and target.id in LABEL_NAMES:
                            offenders.append(f"{where} defines {target.id}")
    assert offenders == []


LOCALISE_LAYERS = (
    "settings",
    "station_assignment",
    "station_occlusion",
    "neighbourhoods",
    "epoch",
    "surface",
    "distance",
    "surface_levels",
    "regions",
    "gaps",
    "ray_silhouettes",
    "rays",
    "interface",
    "station_rays",
    "origin_free",
    "sample_lines",
    "map_planes",
    "map_lines",
    "map_rims",
    "map_outlines",
    "map_fragments",
    "map_sides",
    "map_steps",
    "map_surround",
    "map_parts",
    "map_supports",
    "trajectory_visibility",
    "map_shared",
    "map_faces",
    "map_bodies",
    "map_tops",
    "map_blind",
    "map_scale",
    "map_verdict",
    "map_evidence",
    "map_agreement",
    "coverage",
    "visibility",
    "turned_faces",
    "isolated_clusters",
    "protruding_faces",
    "threshold_band",
    "flying_sight",
    "flying_samples",
    "changed_regions",
    "changes",
)
"""The localisation package's modules, lowest first: each imports only modules before it."""


def test_the_localisation_package_imports_one_way():
    package = CORE / "localise"
    assert sorted(path.stem for path in package.glob("*.py")) == sorted(
        [*LOCALISE_LAYERS, "__init__"]
    )
    offenders = []
    for layer, name in enumerate(LOCALISE_LAYERS):
        for module in imported_modules(package / f"{name}.py"):
            if module == "app.core.localise" or module.startswith("app.core.localise."):
                imported = module.removeprefix("app.core.localise").lstrip(".")
                if imported not in LOCALISE_LAYERS[:layer]:
                    offenders.append(f"{name} imports {module}")
    assert offenders == []


def test_the_docs_list_the_localisation_modules_in_their_import_order():
    """``docs/localisation.md``'s module table says each module imports only those listed
    after it: it lists every module of the package, highest first."""
    text = (REPOSITORY / "docs" / "localisation.md").read_text()
    table = text.split("| module | what it holds |", 1)[1].split("\n\n", 1)[0]
    listed = [line.split("`")[1] for line in table.splitlines() if line.startswith("| `")]
    assert listed == list(reversed(LOCALISE_LAYERS))


def test_the_api_and_the_service_supervisor_load_no_scipy():
    """scipy is imported where it is used (~0.3 CPU s a process): the API process (the FastAPI
    app, with the viewer's routes) and ``scandiff serve``'s supervisor (migrations, recovery,
    storage, which reach the geometry cache and the localiser's settings) never load it; the
    job consumer loads it with the pipeline it preloads."""
    code = (
        "import sys, app.main, app.cli.serve, app.db.migrate, app.jobs.recovery\n"
        "import app.services.storage, app.services.schedules.runs, app.core.cache.geometry\n"
        "print(','.join(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy'))[:200])\n"
    )
    assert printed_by_a_fresh_process(code) == ""


def test_the_localisation_package_gives_its_public_names_on_first_use():
    import app.core.localise as localise
    from app.core.localise.changes import localise_changes

    assert localise.localise_changes is localise_changes
    assert set(localise.__all__) <= set(dir(localise))
    assert all(getattr(localise, name) is not None for name in localise.__all__)
    with pytest.raises(AttributeError, match="no attribute 'made_up'"):
        _ = localise.made_up
