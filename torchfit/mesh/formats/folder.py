"""A rigged animation a user brings: a folder with a manifest, and its loader and writer.

The folder holds ``animation.yaml`` (the manifest) and the files it names. Lengths in the
manifest and the files are in the files' unit; ``unit`` converts them (metres per file
unit, or one of ``m``, ``cm``, ``mm``, ``in``). Example (what ``problem=arm3d`` writes)::

    unit: 1.0
    fps: 24                         # optional: frames per second (default 24; the time
                                    # axis of problem.dynamic=true)
    rest: rest.obj                  # any surface trimesh reads: OBJ, PLY, OFF, STL
    frames: frames.npz              # (F, V, 3) array (key 'frames'), a .npy, or a glob of
                                    # meshes with the rest's vertex count and order,
                                    # e.g. frames/*.obj (natural order: 2 before 10)
    skeleton:                       # (a) bones drive the body ...
      bones: skeleton.npz           #   heads (B, 3), tails (B, 3): rest-pose segments;
                                    #   transforms (F, B, 3, 4): [A | t] per frame and bone,
                                    #   column vectors x' = A x + t on rest positions
                                    #   (or a JSON file with the same keys); names optional
      attach_radius: 0.017          #   material within this distance of a bone follows it
      weights: distance             #   or a .npy (V, B) of per-rest-vertex weights
    # driven:                       # (b) ... or driven surface vertices do
    #   vertices: driven.npy        #   indices (k,), a bool mask (V,), or an inline list
    #   tolerance: 0.002            #   tet vertices this close to the driven region follow it
    regions:                        # optional: per-rest-vertex labels (carried inward)
      labels: regions.npy
      names: [bone, muscle, fat]
    up: z                           # optional: the files' up axis (x, y, z, -x, -y, -z);
                                    # the pictures stand the body on it (none: the body's
                                    # own, problems/body/motion.py)

Every problem of ``problem=animation`` and ``problem=arm3d`` reads its data through
:func:`load_animation`; :func:`write_animation` writes the format. Errors are one line
(:class:`AnimationError`) naming the file, frame or vertex at fault; an array that holds
anything but numbers of its kind (text, objects, complex numbers, bools where numbers are
meant: :func:`check_numbers`) is refused from its header, naming the file, key and dtype.
"""
from __future__ import annotations

import glob
import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ...memory import array_bytes, check_allocation, npy_header, npz_headers
from ..animation import DEFAULT_FPS, UNITS, Animation, AnimationError
from ..rig import DrivenSurface, Skeleton, check_transforms
from ..simplicial import MeshError

MANIFEST = "animation.yaml"
_TOP_KEYS = ("unit", "fps", "rest", "frames", "skeleton", "driven", "regions", "up", "description")
#: the up axes a manifest may name (``up``), as unit vectors
UP_AXES = {f"{sign}{name}": (1.0 if sign != "-" else -1.0) * np.eye(3)[i]
           for i, name in enumerate("xyz") for sign in ("", "+", "-")}
_SKELETON_KEYS = ("bones", "attach_radius", "weights")
_DRIVEN_KEYS = ("vertices", "tolerance")
_REGION_KEYS = ("labels", "names")


# -- reading ------------------------------------------------------------------------------
def _unit(value: Any, manifest: Path) -> float:
    if value is None:
        return 1.0
    if isinstance(value, str):
        if value not in UNITS:
            raise AnimationError(f"{manifest}: unit {value!r} is not one of {sorted(UNITS)} "
                                 "or a number of metres per file unit")
        return UNITS[value]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0 \
            or not np.isfinite(value):
        raise AnimationError(f"{manifest}: unit must be a positive number of metres per file "
                             f"unit (or one of {sorted(UNITS)}), got {value!r}")
    return float(value)


def _up(value: Any, manifest: Path) -> np.ndarray | None:
    if value is None:
        return None
    key = str(value).strip().lower() if isinstance(value, str) else None
    if key not in UP_AXES:
        raise AnimationError(f"{manifest}: up must be one of x, y, z, -x, -y, -z (the files' "
                             f"up axis), got {value!r}")
    return UP_AXES[key].copy()


def _check_keys(section: Any, allowed: tuple[str, ...], where: str, manifest: Path) -> dict:
    if not isinstance(section, dict):
        raise AnimationError(f"{manifest}: '{where}' must be a mapping with keys {list(allowed)}")
    unknown = sorted(set(section) - set(allowed))
    if unknown:
        raise AnimationError(f"{manifest}: unknown key '{unknown[0]}' in {where} (allowed: "
                             f"{', '.join(allowed)})")
    return section


def _require(section: dict, key: str, where: str, manifest: Path) -> Any:
    if section.get(key) is None:
        raise AnimationError(f"{manifest}: missing entry '{key}' in {where}")
    return section[key]


def _file(folder: Path, name: Any, what: str, manifest: Path) -> Path:
    if not isinstance(name, str) or not name:
        raise AnimationError(f"{manifest}: {what} must be a file name, got {name!r}")
    path = (folder / name) if not os.path.isabs(name) else Path(name)
    if not path.is_file():
        raise AnimationError(f"{manifest}: {what} file {path} does not exist")
    return path


def _positive(value: Any, what: str, manifest: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) \
            or not value > 0:
        raise AnimationError(f"{manifest}: {what} must be a positive number (file units), "
                             f"got {value!r}")
    return float(value)


#: The dtype kinds (``numpy.dtype.kind``) an array of numbers may have, by what it holds:
#: coordinates and weights are real numbers (float or integer), labels integers, driven
#: vertices integer indices or a bool mask. Strings, objects, complex numbers (their
#: imaginary part would be dropped), bools where numbers are meant, dates are refused.
NUMBER_KINDS = {"real": "fiu", "integer": "iu", "index": "iub"}
_KIND_NAMES = {"f": "floating point", "i": "integer", "u": "unsigned integer", "b": "bool",
               "c": "complex", "U": "text", "S": "bytes", "O": "Python objects",
               "V": "structured records", "M": "dates", "m": "time spans"}
_WANTED = {"real": "real numbers (float or integer)", "integer": "integers",
           "index": "integer indices or a bool mask"}


def check_numbers(dtype: np.dtype, where: str, numbers: str = "real") -> None:
    """Refuse (one :class:`AnimationError` line naming ``where``: the file and its key) an
    array whose ``dtype`` is not of the kinds :data:`NUMBER_KINDS` allows for ``numbers``."""
    dtype = np.dtype(dtype)
    if dtype.kind not in NUMBER_KINDS[numbers]:
        raise AnimationError(f"{where}: holds {_KIND_NAMES.get(dtype.kind, 'other values')} "
                             f"(dtype {dtype}), but must hold {_WANTED[numbers]}; write it "
                             "again from a numeric array, e.g. np.asarray(values, "
                             f"dtype={'float' if numbers == 'real' else 'int'})")


def _load_array(path: Path, key: str | None = None, numbers: str = "real") -> np.ndarray:
    """The array of a ``.npy`` (or ``key`` of a ``.npz``), its header checked first: numbers
    of the kinds ``numbers`` allows (:func:`check_numbers`), whole, 4 times its float64 size
    within the memory limit (it, its float64 copy, the problem's tensor of it, the simulated
    frames of the same size)."""
    headers = npz_headers(path, str(path), AnimationError) if path.suffix == ".npz" else \
        {None: npy_header(path, str(path), AnimationError)}
    name = key if key in headers else (next(iter(headers)) if len(headers) == 1 else "")
    if name == "":
        raise AnimationError(f"{path}: expected an array named '{key}' (found "
                             f"{', '.join(map(str, headers))})")
    check_numbers(headers[name][1], f"{path}" + ("" if name is None else f" (array '{name}')"),
                  numbers)
    check_allocation(str(path), 4 * array_bytes(headers[name][0], np.float64),
                     f"its array {headers[name][0]} of {headers[name][1]}", AnimationError)
    try:
        if name is None:
            return np.asarray(np.load(path, allow_pickle=False))
        with np.load(path, allow_pickle=False) as data:
            return np.asarray(data[name])
    except Exception as err:  # noqa: BLE001 - numpy raises many kinds for a bad file
        raise AnimationError(f"{path}: cannot read it as a numpy array ({err})") from err


def _check_finite(points: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(points)
    if bad.any():
        index = np.argwhere(bad)[0]
        if points.ndim == 3:
            raise AnimationError(f"{what}: frame {index[0]}, vertex {index[1]} has a NaN or "
                                 "infinite coordinate")
        raise AnimationError(f"{what}: vertex {index[0]} has a NaN or infinite coordinate")


def _read_mesh_vertices(path: Path) -> np.ndarray:
    import trimesh

    try:
        mesh = trimesh.load(str(path), process=False, maintain_order=True, force="mesh")
    except Exception as err:  # noqa: BLE001 - trimesh raises many kinds for a bad file
        raise AnimationError(f"{path}: cannot read it as a mesh ({err})") from err
    return np.asarray(mesh.vertices, dtype=np.float64)


def _read_frames(folder: Path, spec: Any, n_vertices: int, manifest: Path
                 ) -> tuple[np.ndarray, list[str]]:
    if not isinstance(spec, str) or not spec:
        raise AnimationError(f"{manifest}: frames must be a .npy/.npz file or a glob of mesh "
                             f"files, got {spec!r}")
    if spec.endswith((".npy", ".npz")):
        path = _file(folder, spec, "frames", manifest)
        frames = _load_array(path, "frames").astype(np.float64)
        if frames.ndim != 3 or frames.shape[2] != 3:
            raise AnimationError(f"{path}: frames must have shape (frames, vertices, 3), got "
                                 f"{frames.shape}")
        if frames.shape[1] != n_vertices:
            raise AnimationError(f"{path}: frames have {frames.shape[1]} vertices but the rest "
                                 f"surface has {n_vertices}; every frame must have the rest's "
                                 "vertex count and order")
        names = [f"{path.name}[{i}]" for i in range(frames.shape[0])]
    else:
        pattern = spec if os.path.isabs(spec) else str(folder / spec)
        files = sorted(glob.glob(pattern), key=lambda p: [     # natural order: f2 before f10
            int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", os.path.basename(p))])
        if not files:
            raise AnimationError(f"{manifest}: no frame file matches {pattern}")
        check_allocation(pattern, 4 * array_bytes((len(files), n_vertices, 3), np.float64),
                         f"{len(files)} frame files x {n_vertices} vertices", AnimationError)
        frames_list = []
        for name in files:
            vertices = _read_mesh_vertices(Path(name))
            if vertices.shape[0] != n_vertices:
                raise AnimationError(f"{name}: frame has {vertices.shape[0]} vertices but the "
                                     f"rest surface has {n_vertices}; every frame must have the "
                                     "rest's vertex count and order")
            frames_list.append(vertices)
        frames = np.stack(frames_list)
        names = [os.path.basename(f) for f in files]
    if frames.shape[0] == 0:
        raise AnimationError(f"{manifest}: the animation has no frame")
    bad = ~np.isfinite(frames)
    if bad.any():
        f, v = np.argwhere(bad)[0][:2]
        raise AnimationError(f"{manifest}: frame {f} ({names[f]}), vertex {v} has a NaN or "
                             "infinite coordinate")
    return frames, names


def _read_bones(path: Path) -> dict[str, Any]:
    if path.suffix == ".json":
        try:
            raw = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise AnimationError(f"{path}: cannot read it as JSON ({err})") from err
        if not isinstance(raw, dict):
            raise AnimationError(f"{path}: expected an object with heads, tails, transforms")
        data = dict(raw)
    elif path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as npz:
                data = {k: npz[k] for k in npz.files}
        except Exception as err:  # noqa: BLE001
            raise AnimationError(f"{path}: cannot read it as an .npz ({err})") from err
    else:
        raise AnimationError(f"{path}: bones must be an .npz or a .json file")
    allowed = {"heads", "tails", "transforms", "names"}
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise AnimationError(f"{path}: unknown key '{unknown[0]}' (allowed: heads, tails, "
                             "transforms, names)")
    for key in ("heads", "tails", "transforms"):
        if key not in data:
            raise AnimationError(f"{path}: missing entry '{key}'")
    return data


def _read_skeleton(folder: Path, section: dict, manifest: Path, unit: float,
                   n_frames: int, n_vertices: int) -> Skeleton:
    section = _check_keys(section, _SKELETON_KEYS, "skeleton", manifest)
    bones_path = _file(folder, _require(section, "bones", "skeleton", manifest),
                       "skeleton bones", manifest)
    data = _read_bones(bones_path)
    try:
        for key in ("heads", "tails", "transforms"):     # a ragged JSON list: ValueError
            check_numbers(np.asarray(data[key]).dtype, f"{bones_path} ({key})")
        heads = np.asarray(data["heads"], dtype=np.float64)
        tails = np.asarray(data["tails"], dtype=np.float64)
        raw_transforms = np.asarray(data["transforms"], dtype=np.float64)
    except AnimationError:
        raise
    except (TypeError, ValueError) as err:
        raise AnimationError(f"{bones_path}: heads, tails and transforms must be numeric "
                             f"arrays ({err})") from err
    if heads.ndim != 2 or heads.shape[1] != 3 or heads.shape != tails.shape or not len(heads):
        raise AnimationError(f"{bones_path}: heads and tails must both have shape (bones, 3), "
                             f"got {heads.shape} and {tails.shape}")
    for what, arr in (("heads", heads), ("tails", tails)):
        if not np.isfinite(arr).all():
            b = int(np.argwhere(~np.isfinite(arr))[0][0])
            raise AnimationError(f"{bones_path}: bone {b} has a non-finite {what[:-1]}")
    try:
        transforms = check_transforms(raw_transforms, len(heads), n_frames, str(bones_path))
    except AnimationError:
        raise
    except MeshError as err:
        raise AnimationError(str(err)) from err
    transforms = transforms.copy()
    transforms[..., 3] *= unit
    names = [str(n) for n in np.asarray(data.get("names", []), dtype=object).reshape(-1)] \
        or [f"bone{b}" for b in range(len(heads))]
    if len(names) != len(heads):
        raise AnimationError(f"{bones_path}: {len(names)} names for {len(heads)} bones")
    radius = _positive(_require(section, "attach_radius", "skeleton", manifest),
                       "skeleton.attach_radius", manifest) * unit
    weights_spec = section.get("weights", "distance")
    weights = None
    if weights_spec != "distance":
        path = _file(folder, weights_spec, "skeleton weights", manifest)
        weights = _load_array(path, "weights").astype(np.float64)
        if weights.shape != (n_vertices, len(heads)):
            raise AnimationError(f"{path}: skinning weights must have shape ({n_vertices}, "
                                 f"{len(heads)}) (rest vertices x bones), got {weights.shape}")
        if not np.isfinite(weights).all() or (weights < 0).any():
            raise AnimationError(f"{path}: skinning weights must be finite and >= 0")
        sums = weights.sum(axis=1, keepdims=True)
        if (sums <= 0).any():
            v = int(np.flatnonzero(sums[:, 0] <= 0)[0])
            raise AnimationError(f"{path}: vertex {v} has all skinning weights zero")
        weights = weights / sums
    return Skeleton(heads * unit, tails * unit, transforms, radius, weights, names)


def _read_driven(folder: Path, section: dict, manifest: Path, unit: float,
                 n_vertices: int) -> DrivenSurface:
    section = _check_keys(section, _DRIVEN_KEYS, "driven", manifest)
    spec = _require(section, "vertices", "driven", manifest)
    if isinstance(spec, list):
        raw = np.asarray(spec)
        source = f"{manifest} (driven.vertices)"
    else:
        path = _file(folder, spec, "driven vertices", manifest)
        raw = _load_array(path, "vertices", "index")
        source = str(path)
    if raw.dtype == bool:
        if raw.shape != (n_vertices,):
            raise AnimationError(f"{source}: a driven mask must have one entry per rest vertex "
                                 f"({n_vertices}), got shape {raw.shape}")
        mask = raw.copy()
    else:
        if raw.size and not np.issubdtype(raw.dtype, np.integer):
            raise AnimationError(f"{source}: driven vertices must be integer indices or a bool "
                                 "mask")
        indices = raw.astype(np.int64).reshape(-1)
        if indices.size and (indices.min() < 0 or indices.max() >= n_vertices):
            raise AnimationError(f"{source}: driven vertex index out of range [0, {n_vertices})")
        mask = np.zeros(n_vertices, dtype=bool)
        mask[indices] = True
    if not mask.any():
        raise AnimationError(f"{source}: the driven set is empty; name at least one surface "
                             "vertex whose motion is prescribed")
    if mask.all():
        raise AnimationError(f"{source}: the driven set covers every vertex, so nothing is left "
                             "to simulate or fit; drive only part of the surface")
    tolerance = _positive(_require(section, "tolerance", "driven", manifest),
                          "driven.tolerance", manifest) * unit
    return DrivenSurface(mask, tolerance)


def _read_regions(folder: Path, section: dict, manifest: Path,
                  n_vertices: int) -> tuple[np.ndarray, list[str]]:
    section = _check_keys(section, _REGION_KEYS, "regions", manifest)
    path = _file(folder, _require(section, "labels", "regions", manifest), "region labels",
                 manifest)
    labels = _load_array(path, "labels", "integer")
    if labels.shape != (n_vertices,) or not np.issubdtype(labels.dtype, np.integer):
        raise AnimationError(f"{path}: region labels must be integers, one per rest vertex "
                             f"({n_vertices},), got {labels.dtype} {labels.shape}")
    labels = labels.astype(np.int64)
    if labels.min() < 0 or labels.max() >= n_vertices:     # at most one region per vertex
        raise AnimationError(f"{path}: region labels must lie in 0..{n_vertices - 1} (one per "
                             f"rest vertex at most), got {labels.min()}..{labels.max()}")
    n_regions = int(labels.max()) + 1
    names = section.get("names") or [f"region{r}" for r in range(n_regions)]
    if not isinstance(names, list) or len(names) != n_regions:
        raise AnimationError(f"{manifest}: regions.names must list {n_regions} names "
                             f"(labels 0..{n_regions - 1})")
    return labels, [str(n) for n in names]


def _manifest_path(path: str | Path) -> Path:
    """The manifest of an animation folder (or the manifest file itself)."""
    path = Path(path).expanduser()
    if path.is_dir():
        path = path / MANIFEST
    if not path.is_file():
        raise AnimationError(f"no animation manifest at {path}: problem.path must be a folder "
                             f"holding {MANIFEST} (see docs/guide/formats.md)")
    from .sniff import refusal

    refused = refusal(path)
    if refused:
        raise AnimationError(refused)
    return path


def load_animation(path: str | Path) -> Animation:
    """Read and check an animation folder (or its manifest); every length in metres.

    Raises :class:`AnimationError` (one line) for a missing file, an unknown manifest key
    or missing entry, a frame with another vertex count than the rest (naming the file),
    NaN or infinite coordinates (naming frame and vertex), an empty driven set or one that
    covers every vertex, a non-finite bone transform.
    """
    import yaml

    from ..surface import load_surface, surface_warnings

    manifest = _manifest_path(path)
    folder = manifest.parent
    try:
        raw = yaml.safe_load(manifest.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        why = f"not UTF-8 text (byte {err.start}); save it as UTF-8" if isinstance(
            err, UnicodeDecodeError) else f"cannot read the manifest ({err})"
        raise AnimationError(f"{manifest}: {why}") from err
    spec = _check_keys(raw if raw is not None else {}, _TOP_KEYS, "the manifest", manifest)
    unit = _unit(spec.get("unit"), manifest)
    rest_file = _file(folder, _require(spec, "rest", "the manifest", manifest), "rest surface",
                      manifest)
    try:
        surface = load_surface(rest_file)
    except MeshError as err:
        raise AnimationError(str(err)) from err
    rest = np.asarray(surface.vertices, dtype=np.float64)
    faces = np.asarray(surface.faces, dtype=np.int64)
    frames, names = _read_frames(folder, _require(spec, "frames", "the manifest", manifest),
                                 rest.shape[0], manifest)
    has_skeleton, has_driven = spec.get("skeleton") is not None, spec.get("driven") is not None
    if has_skeleton == has_driven:
        raise AnimationError(f"{manifest}: give exactly one of 'skeleton' (bones drive the body) "
                             "or 'driven' (surface vertices drive it)" if has_skeleton else
                             f"{manifest}: missing entry 'skeleton' or 'driven' (what drives "
                             "the body)")
    skeleton = driven = None
    if has_skeleton:
        skeleton = _read_skeleton(folder, spec["skeleton"], manifest, unit, frames.shape[0],
                                  rest.shape[0])
    else:
        driven = _read_driven(folder, spec["driven"], manifest, unit, rest.shape[0])
    labels, region_names = None, []
    if spec.get("regions") is not None:
        labels, region_names = _read_regions(folder, spec["regions"], manifest, rest.shape[0])
    return Animation(manifest, rest * unit, faces, frames * unit, unit, skeleton, driven,
                     labels, region_names, names, surface_warnings(surface),
                     up=_up(spec.get("up"), manifest), fps=_fps(spec.get("fps"), manifest))


def _fps(value: Any, manifest: Path) -> float:
    if value is None:
        return DEFAULT_FPS
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0 \
            or not np.isfinite(value):
        raise AnimationError(f"{manifest}: fps must be a positive number of frames per "
                             f"second, got {value!r}")
    return float(value)


# -- writing ------------------------------------------------------------------------------
def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A plain OBJ (``v``/``f`` lines, vertex order kept, 17 significant digits so that the
    positions read back bit for bit)."""
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    Path(path).write_text("\n".join(lines) + "\n")


#: the files :func:`write_animation` writes: a folder holding only these is one it may replace
WRITTEN_FILES = frozenset({MANIFEST, "rest.obj", "frames.npz", "skeleton.npz", "weights.npy",
                           "driven.npy", "regions.npy"})


def check_replaceable(folder: str | Path) -> None:
    """Raise :class:`AnimationError` (one line) unless ``folder`` may be replaced by a written
    animation: absent, an empty folder, or a folder holding only the files
    :func:`write_animation` writes (:data:`WRITTEN_FILES`). A plain file, or a folder with
    anything else in it (a user's notes, a hand-made animation's frame meshes), is never
    deleted to make room."""
    folder = Path(folder)
    if not (folder.exists() or folder.is_symlink()):
        return
    if not folder.is_dir() or folder.is_symlink():
        raise AnimationError(f"{folder} exists and is not a folder; an animation folder would "
                             "replace it: name a new folder (or a .usda/.glb file)")
    others = sorted(e.name for e in folder.iterdir() if e.name not in WRITTEN_FILES
                    or not e.is_file())
    if others:
        shown = ", ".join(others[:3]) + (f" and {len(others) - 3} more" if len(others) > 3 else "")
        raise AnimationError(f"{folder} holds files torchfit did not write ({shown}); an "
                             "animation is written only into a new or empty folder or over "
                             "one torchfit wrote: name a new folder, or move those files")


def replace_folder(new: Path, folder: Path) -> None:
    """Put the written folder ``new`` at ``folder`` (checked by :func:`check_replaceable`):
    the old one is renamed aside, the new one renamed in, then the old one removed (a kill in
    between leaves the old animation beside, hidden, never half of either)."""
    if not folder.exists():
        os.replace(new, folder)
        return
    check_replaceable(folder)
    aside = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old.", dir=folder.parent))
    os.replace(folder, aside / "old")
    os.replace(new, folder)
    shutil.rmtree(aside, ignore_errors=True)


def user_permissions(path: Path) -> None:
    """Give a folder made by ``tempfile.mkdtemp`` (mode 0700) the mode a plain ``mkdir``
    gives (0777 less the umask): the written animation is the user's, not private."""
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(path, 0o777 & ~mask)


def write_animation(folder: str | Path, rest_vertices: np.ndarray, faces: np.ndarray,
                    frames: np.ndarray, *, skeleton: Skeleton | None = None,
                    driven: DrivenSurface | None = None,
                    region_labels: np.ndarray | None = None,
                    region_names: list[str] | None = None, description: str = "",
                    up: str | None = None, fps: float | None = None) -> Path:
    """Write an animation folder in the format above (lengths in metres, ``unit: 1.0``;
    ``up``: the manifest's up axis, one of :data:`UP_AXES`, or ``None``: none written;
    ``fps`` written where given).

    The folder is written whole into a temporary sibling and renamed into place, so a
    killed process never leaves a half-written animation. An existing ``folder`` is replaced
    only where :func:`check_replaceable` allows (else :class:`AnimationError`, nothing
    written). Returns the manifest path.
    """
    if (skeleton is None) == (driven is None):
        raise ValueError("give exactly one of skeleton or driven")
    folder = Path(folder)
    check_replaceable(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    user_permissions(tmp)
    try:
        write_obj(tmp / "rest.obj", np.asarray(rest_vertices, dtype=np.float64),
                  np.asarray(faces, dtype=np.int64))
        np.savez_compressed(tmp / "frames.npz", frames=np.asarray(frames, dtype=np.float64))
        manifest: dict[str, Any] = {}
        if description:
            manifest["description"] = description
        manifest.update({"unit": 1.0, "rest": "rest.obj", "frames": "frames.npz"})
        if up is not None:
            if up.strip().lower() not in UP_AXES:
                raise ValueError(f"up must be one of x, y, z, -x, -y, -z, got {up!r}")
            manifest["up"] = up.strip().lower()
        if fps is not None:
            manifest["fps"] = float(fps)
        if skeleton is not None:
            np.savez(tmp / "skeleton.npz", heads=skeleton.heads, tails=skeleton.tails,
                     transforms=skeleton.transforms, names=np.asarray(skeleton.names))
            section: dict[str, Any] = {"bones": "skeleton.npz",
                                       "attach_radius": float(skeleton.attach_radius)}
            if skeleton.weights is not None:
                np.save(tmp / "weights.npy", skeleton.weights)
                section["weights"] = "weights.npy"
            else:
                section["weights"] = "distance"
            manifest["skeleton"] = section
        else:
            np.save(tmp / "driven.npy", driven.indices)
            manifest["driven"] = {"vertices": "driven.npy", "tolerance": float(driven.tolerance)}
        if region_labels is not None:
            np.save(tmp / "regions.npy", np.asarray(region_labels, dtype=np.int64))
            manifest["regions"] = {"labels": "regions.npy", "names": list(region_names or [])}
        import yaml

        (tmp / MANIFEST).write_text(yaml.safe_dump(manifest, sort_keys=False))
        replace_folder(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder / MANIFEST
