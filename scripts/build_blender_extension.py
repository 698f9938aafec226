"""Build the torchfit Blender extension's installable zip from scripts/blender/torchfit_blender.

    python scripts/build_blender_extension.py [--out dist/]     # writes torchfit-<version>.zip

The zip is what Blender's ``blender --command extension build`` makes: the package's files
at the zip's root (``blender_manifest.toml`` beside ``__init__.py``), no caches. Install it
in Blender 4.2+ with Edit > Preferences > Get Extensions > Install from Disk
(docs/guide/blender.md).
"""
from __future__ import annotations

import argparse
import re
import sys
import zipfile
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent / "blender" / "torchfit_blender"


def manifest_field(text: str, key: str) -> str:
    """A top-level string field of ``blender_manifest.toml`` (read without a TOML parser:
    the file's own keys are plain ``key = "value"`` lines)."""
    match = re.search(rf'^{key}\s*=\s*"([^"]*)"', text, re.MULTILINE)
    if match is None:
        raise SystemExit(f"error: {PACKAGE / 'blender_manifest.toml'} has no {key}")
    return match.group(1)


def build(out_dir: str | Path) -> Path:
    """Write ``<out_dir>/<id>-<version>.zip``; returns its path."""
    manifest = (PACKAGE / "blender_manifest.toml").read_text()
    name = f"{manifest_field(manifest, 'id')}-{manifest_field(manifest, 'version')}.zip"
    out = Path(out_dir) / name
    out.parent.mkdir(parents=True, exist_ok=True)
    files = sorted(p for p in PACKAGE.rglob("*") if p.is_file()
                   and "__pycache__" not in p.parts and p.suffix not in (".pyc", ".pyo"))
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        for path in files:
            archive.write(path, path.relative_to(PACKAGE).as_posix())
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="dist", help="folder for the zip (default: dist)")
    args = parser.parse_args(argv)
    print(build(args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
