"""``scandiff compare`` start-up: reading point files and planning tiles need numpy alone;
scipy and scikit-learn (about 0.5 CPU s of imports) load on a thread while the pair is read,
and a refused file exits cleanly (status 2) after that thread."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from app.testing.paths import PROJECT_ROOT

HEAVY = ("scipy", "sklearn")


def _heavy_modules_after(code: str) -> list[str]:
    """The scipy/scikit-learn modules a fresh interpreter holds after running ``code``."""
    probe = (
        f"import json, sys\n{code}\n"
        f"print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in {HEAVY!r})))"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], cwd=PROJECT_ROOT, capture_output=True, text=True, check=True
    )
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_reading_files_and_planning_tiles_import_no_scipy() -> None:
    code = (
        "import app.core.formats, app.core.formats.streamed, app.core.tiling.lean\n"
        "import app.core.tiling.plan, app.core.tiling.pair_files"
    )
    assert _heavy_modules_after(code) == []


def test_a_file_that_is_not_a_point_cloud_is_refused_with_status_2_every_time(
    tmp_path: Path,
) -> None:
    """The refusal never crashes: the comparison's stack, imported on a thread while the pair
    is read, is waited for before the command returns (exiting mid-import died of SIGSEGV)."""
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"\x00\x01garbage")
    code = f"from app.cli import main\nraise SystemExit(main(['compare', *[{str(garbage)!r}] * 2]))"
    for _ in range(6):
        result = subprocess.run(
            [sys.executable, "-c", code], cwd=PROJECT_ROOT, capture_output=True, text=True
        )
        assert result.returncode == 2, result.stderr[-2000:]
        assert "not a PLY file" in result.stderr


def test_the_untiled_comparison_stack_imports_no_scipy_until_the_comparison_runs() -> None:
    """``scandiff compare`` imports the comparison's stack (``app.core.tiling.compare``) after
    reading the clouds, in its serial start-up: scipy (~0.2 CPU s with scipy.sparse and
    csgraph) loads on first use instead, the tile merge's included, which an untiled
    comparison never calls."""
    assert _heavy_modules_after("import app.core.tiling.compare, app.core.pipeline") == []


def test_the_warm_up_thread_loads_the_region_clustering_graphs() -> None:
    """The detectors' warm-up thread (started as the comparison loads its pair, beside the
    neighbour searches) loads scipy's graph components too, which the localiser's region
    clustering imports on first use on both sides' threads."""
    code = "from app.core.detectors import warm_up\nwarm_up().join()"
    assert "scipy.sparse.csgraph" in _heavy_modules_after(code)
