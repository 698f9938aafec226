"""What a ``problem.path`` file is, by its first bytes and its suffix, and the one line for a
file torchfit does not read (FBX, Alembic, a bare mesh) saying what to export instead.

:func:`sniff` reads at most the first 4 KiB and returns a :class:`FileKind`: its name
(``fbx``, ``alembic``, ``hdf5``, ``gltf``, ``usd``, ``mesh``, ``text``, ``binary``), what it is
in words and which reader takes it (``usd``, ``gltf``, ``folder``; ``""``: none). The content
decides where it is recognised (magic bytes: ``Kaydara FBX Binary``, an ASCII FBX's
``; FBX`` header, Alembic's ``Ogawa``, the HDF5 signature, ``glTF``, USD's ``PXR-USDC`` crate
and ``#usda`` text, PLY's ``ply``, OFF's ``OFF``, an ASCII STL's ``solid``); the suffix
where the content has no magic (an OBJ, a binary STL, a ``.gltf``'s JSON, a ``.usdz`` zip).
:func:`refusal` is the message for a file no reader takes, or whose suffix names another
reader than its content (a ``.usda`` that is binary FBX is named as FBX), else ``None``.
Nothing here imports a reader or raises.
"""
from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

#: how much of a file :func:`sniff` reads
HEAD_BYTES = 4096
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
GLTF_SUFFIXES = (".gltf", ".glb")
MESH_SUFFIXES = {".obj": "OBJ", ".ply": "PLY", ".stl": "STL", ".off": "OFF"}

#: what to export instead, for every refusal (one sentence, no line break)
EXPORT = ("export the rigged, animated character as a USD stage with UsdSkel or as a glTF 2.0 "
          "skin from your DCC (Blender: File > Export > Universal Scene Description, or "
          "File > Export > glTF 2.0 (.glb); Maya: File > Export All... > USD Export; Houdini: "
          "a USD ROP) and give that file as problem.path, or write the folder format of "
          "docs/guide/formats.md")


@dataclasses.dataclass(frozen=True)
class FileKind:
    """A file as :func:`sniff` sees it: ``name``, ``what`` (words), ``reader`` (``""``: none)."""

    name: str
    what: str
    reader: str


def suffix_reader(path: str | Path) -> str:
    """The reader a path's suffix names: ``usd``, ``gltf`` or ``folder``."""
    suffix = Path(path).suffix.lower()
    return "usd" if suffix in USD_SUFFIXES else "gltf" if suffix in GLTF_SUFFIXES else "folder"


def _uint32(head: bytes, at: int) -> int | None:
    return struct.unpack_from("<I", head, at)[0] if len(head) >= at + 4 else None


def sniff(path: str | Path) -> FileKind:
    """The kind of the file at ``path`` (an existing file) from its first bytes and suffix."""
    path = Path(path)
    with open(path, "rb") as stream:
        head = stream.read(HEAD_BYTES)
    suffix = path.suffix.lower()
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    if head.startswith(b"Kaydara FBX Binary"):
        version = _uint32(head, 23)
        return FileKind("fbx", "a binary FBX file" + (
            f" (FBX {version // 1000}.{version % 1000 // 100})" if version else ""), "")
    if text.startswith(b"; FBX"):
        return FileKind("fbx", "an ASCII FBX file (" + text.split(b"\n")[0][2:].decode(
            "ascii", "replace").strip() + ")", "")
    if head.startswith(b"Ogawa"):
        return FileKind("alembic", "an Alembic archive (Ogawa)", "")
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        if suffix == ".abc":
            return FileKind("alembic", "an Alembic archive (HDF5)", "")
        return FileKind("hdf5", "an HDF5 file", "")
    if head.startswith(b"glTF"):
        version = _uint32(head, 4)
        return FileKind("gltf", "a binary glTF file" + (f" (glTF {version})" if version else ""),
                        "gltf")
    if head.startswith(b"PXR-USDC"):
        return FileKind("usd", "a binary USD file (crate, PXR-USDC)", "usd")
    if head.startswith(b"#usda"):
        return FileKind("usd", "a USD text file (#usda)", "usd")
    if head.startswith(b"PK\x03\x04") and suffix == ".usdz":
        return FileKind("usd", "a USDZ package", "usd")
    if suffix == ".gltf" and text.startswith(b"{"):
        return FileKind("gltf", "a glTF JSON file", "gltf")
    if head.startswith((b"ply\n", b"ply\r\n")):
        return FileKind("mesh", "a PLY mesh", "")
    if head.startswith(b"OFF") and suffix in ("", ".off"):
        return FileKind("mesh", "an OFF mesh", "")
    if text.startswith(b"solid") and suffix == ".stl":
        return FileKind("mesh", "an ASCII STL mesh", "")
    if suffix == ".stl":
        count = _uint32(head, 80)
        if count is not None and path.stat().st_size == 84 + 50 * count:
            return FileKind("mesh", "a binary STL mesh", "")
    if suffix == ".obj" and any(line.split(b" ", 1)[0] in (b"v", b"f", b"vn", b"vt", b"o")
                                for line in text.splitlines()[:200]):
        return FileKind("mesh", "an OBJ mesh", "")
    if b"\x00" in head:
        return FileKind("binary", "a binary file", "")
    return FileKind("text", "a text file", "folder")


def refusal(path: str | Path) -> str | None:
    """The one line (without ``error:``) for a file torchfit reads with no reader, or whose
    suffix names another reader than its content; ``None`` for a folder, a missing file or a
    file the suffix's reader is to read. ``path`` is named absolute."""
    path = Path(path).expanduser()
    if not path.is_file():
        return None
    kind = sniff(path)
    where = path.absolute()
    named = suffix_reader(path)
    if path.stat().st_size == 0:                # an empty .fbx was read as a manifest
        return (f"{where} is an empty file; problem.path must be an animation folder, a USD "
                f"stage or a glTF file: {EXPORT}")
    if path.suffix.lower() in (".fbx", ".abc") and kind.name not in ("fbx", "alembic", "hdf5"):
        return (f"{where} ends in '{path.suffix}' but is {kind.what}, not an "
                f"{'FBX file' if path.suffix.lower() == '.fbx' else 'Alembic archive'}; "
                f"torchfit reads neither: {EXPORT}")
    if kind.name == "fbx":
        return (f"{where} is {kind.what}, which torchfit does not read (Autodesk's format has "
                f"no open reader); {EXPORT}; an FBX can be opened in Blender first "
                "(File > Import > FBX)")
    if kind.name == "alembic":
        return (f"{where} is {kind.what}: a point cache without a rig, which torchfit does not "
                f"read; {EXPORT} (a point-cache stage needs its driven vertices, "
                "primvars:torchfit:driven)")
    if kind.name == "mesh":
        return (f"{where} is {kind.what}: one surface without a rig or frames, which is not an "
                "animation; name it as 'rest' in an animation folder's animation.yaml with its "
                f"frames and skeleton (docs/guide/formats.md), or {EXPORT.split(' and give')[0]}")
    if kind.reader and kind.reader != named:
        rename = {"usd": ".usd", "gltf": ".glb" if kind.name == "gltf" and "binary" in kind.what
                  else ".gltf"}.get(kind.reader, "")
        return (f"{where} is {kind.what} but its suffix '{path.suffix}' says otherwise; rename "
                f"it to end in {rename}" if rename else
                f"{where} is {kind.what}, not a USD stage or a glTF file; give the animation "
                f"folder (holding animation.yaml) or a .usd/.usda/.usdc/.glb/.gltf file")
    if named == "folder" and kind.name in ("binary", "hdf5"):
        return (f"{where} is {kind.what}, not an animation manifest (animation.yaml); "
                f"problem.path must be an animation folder, a USD stage or a glTF file: {EXPORT}")
    return None
