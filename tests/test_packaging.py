"""Packaging: pyproject.toml lists every package of mvrecon/ and ships the top-level scenes/ as
mvrecon/catalog/, where an installed mvrecon finds its scene catalog."""

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import mvrecon
from mvrecon.scenes.catalog import CATALOG_DIR, list_scenes

ROOT = Path(mvrecon.__file__).resolve().parents[1]


def _setuptools_table() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_package_folder_is_listed():
    listed = set(_setuptools_table()["packages"])
    folders = {
        ".".join(init.parent.relative_to(ROOT).parts)
        for init in (ROOT / "mvrecon").rglob("__init__.py")
        if "__pycache__" not in init.parts
    }
    assert listed - {"mvrecon.catalog"} == folders


def test_the_catalog_ships_from_the_top_level_scenes_folder():
    table = _setuptools_table()
    assert table["package-dir"] == {"mvrecon.catalog": "scenes"}
    assert table["package-data"]["mvrecon.catalog"] == ["*.toml"]
    assert CATALOG_DIR == ROOT / "scenes"  # a checkout (or an editable install) reads the folder itself
    assert len(list_scenes()) >= 20 and (ROOT / "scenes" / "object_orbit_small.toml").is_file()


def test_an_installed_package_finds_its_catalog(tmp_path):
    """The layout pip installs: mvrecon/ with the TOML files in mvrecon/catalog/, and no scenes/ beside it."""
    site = tmp_path / "site"
    shutil.copytree(ROOT / "mvrecon", site / "mvrecon", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "scenes", site / "mvrecon" / "catalog")
    code = ("from mvrecon.scenes.catalog import CATALOG_DIR, list_scenes\n"
            "print(CATALOG_DIR)\nprint(*list_scenes())")
    env = {**os.environ, "PYTHONPATH": str(site)}
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert Path(out[0]) == site / "mvrecon" / "catalog"
    assert out[1].split() == list_scenes()
