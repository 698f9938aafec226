"""scripts/build_blender_extension.py: the zip holds the extension's files at its root, the
manifest as Blender's extension rules want it (installing it in Blender: blender/test_ui.py)."""
from __future__ import annotations

import importlib.util
import tomllib
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _build_module():
    spec = importlib.util.spec_from_file_location(
        "build_blender_extension", REPO / "scripts" / "build_blender_extension.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_zip_has_the_manifest_at_its_root_and_no_caches(tmp_path):
    path = _build_module().build(tmp_path)
    assert path.name == "torchfit-0.1.0.zip"
    names = zipfile.ZipFile(path).namelist()
    assert {"blender_manifest.toml", "__init__.py", "command.py", "job.py", "results.py",
            "ui.py"} <= set(names)
    assert not any("__pycache__" in n or n.endswith(".pyc") or "/" in n for n in names)
    manifest = tomllib.loads(zipfile.ZipFile(path).read("blender_manifest.toml").decode())
    assert manifest["schema_version"] == "1.0.0" and manifest["id"] == "torchfit"
    assert manifest["type"] == "add-on" and manifest["blender_version_min"] == "4.2.0"
    for key in ("version", "name", "tagline", "maintainer", "license"):
        assert manifest[key]
