"""The data directory's layout: where each file lives, and stored paths that lead outside."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from app.config import Settings
from app.kit.data_layout import DataLayout, StoredPathError


def test_every_place_is_under_the_data_directory(tmp_path: Path) -> None:
    layout = Settings(data_dir=tmp_path).data_layout
    assert layout == DataLayout(tmp_path.resolve())
    assert layout.scan_storage_path("s1", "c1", "ply") == "scans/s1/c1.ply"
    assert layout.resolve("scans/s1/c1.ply") == tmp_path / "scans" / "s1" / "c1.ply"
    assert layout.labels_file("j1") == tmp_path / "results" / "j1" / "labels.npz"
    assert layout.stored_form(layout.labels_file("j1")) == "results/j1/labels.npz"
    assert layout.site_scans_dir("s1") == layout.scans_dir / "s1"
    assert Settings(data_dir=tmp_path).sqlalchemy_url == f"sqlite:///{tmp_path}/scandiff.sqlite3"
    assert Settings(data_dir=tmp_path).queue_path == tmp_path / "queue.sqlite3"


def test_an_absolute_path_inside_is_read_as_it_is(tmp_path: Path) -> None:
    layout = DataLayout(tmp_path)
    inside = tmp_path / "scans" / "s1" / "c1.ply"
    assert layout.resolve(str(inside)) == inside


@pytest.mark.parametrize(
    "stored",
    ["../elsewhere.ply", "scans/../../elsewhere.ply", "/etc/passwd", "scans/a\x00b.ply"],
)
def test_a_stored_path_leading_outside_is_refused(tmp_path: Path, stored: str) -> None:
    layout = DataLayout(tmp_path / "data")
    with pytest.raises(StoredPathError, match=r"outside the data directory|NUL"):
        layout.resolve(stored)


def test_a_symbolic_link_out_of_the_data_directory_is_refused(tmp_path: Path) -> None:
    layout = DataLayout(tmp_path / "data")
    (tmp_path / "data" / "scans").mkdir(parents=True)
    (tmp_path / "secret.ply").write_text("not yours")
    (tmp_path / "data" / "scans" / "link.ply").symlink_to(tmp_path / "secret.ply")
    with pytest.raises(StoredPathError):
        layout.resolve("scans/link.ply")
    with pytest.raises(StoredPathError):
        layout.stored_form(tmp_path / "data" / "scans" / "link.ply")


def test_the_uploads_and_the_workers_pid_files_are_the_layouts(tmp_path: Path) -> None:
    layout = DataLayout(tmp_path)
    assert Settings(data_dir=tmp_path).uploads_dir == tmp_path / "uploads"
    assert layout.worker_pid_file(42) == tmp_path / "run" / "worker-42"
    assert layout.worker_pid_files() == {}  # no run directory yet
    layout.run_dir.mkdir()
    layout.worker_pid_file(42).touch()
    (layout.run_dir / "doorbell").touch()
    assert layout.worker_pid_files() == {"42": layout.worker_pid_file(42)}


APP = Path(__file__).resolve().parents[2] / "app"


def _joins_the_data_directory(node: ast.AST) -> bool:
    """``<...>data_dir / <anything>``: a place under the data directory named outside the layout."""
    if not (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div)):
        return False
    left = node.left
    return (left.attr if isinstance(left, ast.Attribute) else getattr(left, "id", "")) == "data_dir"


def test_no_module_but_the_layout_joins_the_data_directory_with_a_name() -> None:
    """Every place under ``data_dir`` is named in :class:`DataLayout` alone (the harness and the
    settings named ``run/``, ``admin-token`` and ``uploads/`` again)."""
    offenders = [
        f"{path.relative_to(APP.parent)}:{node.lineno}"
        for path in sorted(APP.rglob("*.py"))
        if path != APP / "kit" / "data_layout.py"
        for node in ast.walk(ast.parse(path.read_text()))
        if _joins_the_data_directory(node)
    ]
    assert offenders == []
