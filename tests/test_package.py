"""``dfvo`` is a regular package (its own ``__init__.py``), so a second install or checkout cannot merge into it as
namespace packages do, and its version has one home."""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import dfvo

PACKAGE = Path(__file__).resolve().parents[1] / "dfvo"


def test_dfvo_is_one_regular_package_from_this_checkout():
    assert dfvo.__file__ is not None and Path(dfvo.__file__) == PACKAGE / "__init__.py"
    assert list(dfvo.__path__) == [str(PACKAGE)]


def test_every_folder_with_code_is_a_regular_package():
    folders = {p.parent for p in PACKAGE.rglob("*.py")}
    assert [str(f) for f in sorted(folders) if not (f / "__init__.py").is_file()] == []


def test_the_installed_version_is_the_package_version():
    assert importlib.metadata.version("dfvo") == dfvo.__version__
