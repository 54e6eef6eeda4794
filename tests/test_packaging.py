"""The package installs as one import namespace: nothing generic lands at the top of site-packages."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SUBPACKAGES = ("losses", "rasterizers", "recon", "cli", "experiments")


def _from_checkout() -> bool:
    """True when ``autoalign`` is imported from this source tree (an editable developer install)."""
    import autoalign

    return Path(autoalign.__file__).resolve().is_relative_to(REPO)


@pytest.mark.slow
def test_wheel_holds_only_the_autoalign_namespace(tmp_path: Path) -> None:
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(tmp_path)], check=True)
    (whl,) = tmp_path.glob("autoalign-*.whl")
    names = zipfile.ZipFile(whl).namelist()
    tops = {n.split("/")[0] for n in names}
    assert tops == {"autoalign", next(t for t in tops if t.endswith(".dist-info"))}
    for sub in SUBPACKAGES:
        assert f"autoalign/{sub}/__init__.py" in names
    assert "autoalign/data/example/scene/scene_camera.json" in names
    for page in ("index.html", "label.js", "label.css"):  # autoalign label's page
        assert f"autoalign/cli/label_page/{page}" in names
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    assert "autoalign = autoalign.cli.main:entry" in zipfile.ZipFile(whl).read(entry).decode()


def test_subpackages_import_under_autoalign_only(tmp_path: Path) -> None:
    """In a fresh interpreter outside the checkout, autoalign.X imports and bare X does not."""
    code = ("import importlib, importlib.util, sys; subs = sys.argv[1:]; "
            "[importlib.import_module('autoalign.' + s) for s in subs]; "
            "print([s for s in subs if importlib.util.find_spec(s) is not None])")
    out = subprocess.run([sys.executable, "-c", code, *SUBPACKAGES], cwd=tmp_path, capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.skipif(_from_checkout(), reason="developer checkout (pip install -e); CI runs the non-editable install")
def test_installed_layout_is_nested() -> None:
    import autoalign
    import autoalign.losses

    root = Path(autoalign.__file__).parent
    assert Path(autoalign.losses.__file__).parent == root / "losses"
    assert not root.is_relative_to(REPO), "tests must run against the installed package"


def test_console_script_is_installed_and_runs() -> None:
    import shutil

    import autoalign

    exe = shutil.which("autoalign")
    assert exe is not None, "the `autoalign` command is not on PATH after installation"
    out = subprocess.run([exe, "--version"], capture_output=True, text=True, check=True)
    assert autoalign.__version__ in out.stdout + out.stderr
