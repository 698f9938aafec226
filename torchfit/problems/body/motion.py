"""What of a body's motion the outputs show: the most deformed frame, the camera, the most
strained region.

All are rotation-equivariant (a rotated body and animation give the same frame, a
rotated camera, the same tetrahedra), so the pictures of a rotated body are the same
pictures (docs/notes/axes.md), except where the file names its up axis: then the picture
stands the body on it, as the TD's DCC tool does:

* :func:`most_deformed_frame`: the frame whose target surface lies farthest (mean over the
  vertices) from the rest surface moved rigidly onto it (best rotation and translation,
  Kabsch): deformation, not a rigid turn of the whole body nor a root bone's rotation.
* :func:`picture_up`: the pictures' up: the file's up axis where the file has one (a USD
  stage's ``upAxis``, glTF's +Y, the folder manifest's ``up``: ``Animation.up``), else the
  body's own: its long axis (the grid's ``a2``) pointing from the rig's root joint towards
  the joints of its largest branch (:func:`rig_up`: a standing character's pelvis to its
  spine, neck, head and arms rather than to its two legs; the procedural arm's shoulder to
  its wrist), else (no rig, or a branch across the long axis) ``a2`` with its own sign
  (the third moment: :mod:`.frame`).
* :func:`view_axes`: "up" is that direction, exactly; the camera looks across it along the
  direction in which the target moves least (the smallest principal axis of the
  displacements over every frame and vertex, within the plane across up), so the plane of
  motion faces it; the sign is chosen so that the mean motion goes to the right.
* :func:`most_strained_cells`: the tetrahedra of largest Green strain in a pose (for bodies
  whose rig has no joint: the region whose volume change the run reports).
"""
from __future__ import annotations

import numpy as np

#: the share of the tetrahedra in the most strained region
STRAINED_SHARE = 0.1


def most_deformed_frame(rest: np.ndarray, frames: np.ndarray) -> int:
    """Index of the frame of ``frames`` ``(F, V, 3)`` deformed most from ``rest`` ``(V, 3)``
    once each frame's best rigid motion is removed (module doc)."""
    rest = np.asarray(rest, dtype=np.float64)
    frames = np.asarray(frames, dtype=np.float64)
    centred_rest = rest - rest.mean(axis=0)
    centred = frames - frames.mean(axis=1, keepdims=True)                   # (F, V, 3)
    cross = np.einsum("vi,fvj->fij", centred_rest, centred)                 # (F, 3, 3)
    u, _, vt = np.linalg.svd(cross)
    det = np.sign(np.linalg.det(np.einsum("fij,fjk->fik", u, vt)))
    fix = np.ones((len(frames), 3))
    fix[:, 2] = det
    rotation = np.einsum("fji,fj,fkj->fik", vt, fix, u)     # R = V diag(1, 1, d) U^T
    moved = np.einsum("fij,vj->fvi", rotation, centred_rest)
    residual = np.linalg.norm(centred - moved, axis=-1).mean(axis=1)        # (F,)
    return int(np.argmax(residual))


def view_axes(rest: np.ndarray, frames: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Camera axes ``(3, 3)``, rows ``right, depth, up`` (right-handed): a picture in these
    coordinates seen from ``-depth`` shows the motion side-on with ``up`` up (module doc).

    ``rest`` ``(V, 3)``, ``frames`` ``(F, V, 3)``; ``up`` ``(3,)`` the picture's up
    (:func:`picture_up`; any length), the last row exactly (normalised)."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    motion = (np.asarray(frames, dtype=np.float64) - np.asarray(rest)[None]).reshape(-1, 3)
    centred = motion - motion.mean(axis=0)
    across = np.eye(3) - np.outer(up, up)
    spread = across @ (centred.T @ centred) @ across
    # up itself gets the largest eigenvalue: the least motion is sought across it
    spread += (np.trace(spread) + 1.0) * np.outer(up, up)
    _, vectors = np.linalg.eigh(spread)
    depth = vectors[:, 0] - (vectors[:, 0] @ up) * up         # the direction of least motion
    depth /= np.linalg.norm(depth)
    right = np.cross(depth, up)
    if motion.mean(axis=0) @ right < 0:
        depth, right = -depth, -right
    return np.stack([right, depth, up])


#: a branch direction within this cosine of the plane across the long axis says nothing
_ACROSS = 0.2


def rig_up(skeleton, long_axis: np.ndarray) -> np.ndarray | None:
    """``long_axis`` ``(3,)`` signed to point from the rig's root joint towards the mean
    tail of the bones of its largest branch, or ``None`` (no skeleton, or that direction
    within :data:`_ACROSS` of the plane across the long axis).

    The root joint is the head of the first bone whose head is no other bone's tail; a
    branch is a bone starting there and every bone beyond it (a bone follows the one whose
    tail is its head); the largest has the most bones (the first of equals). A standing
    character's pelvis has its legs (a few bones each) and its spine (spine, neck, head,
    both arms: most of the rig) below and above it; a rig rooted at the floor has one
    branch, above; an arm rooted at the shoulder one, towards the hand."""
    if skeleton is None or skeleton.n_bones == 0:
        return None
    heads, tails = np.asarray(skeleton.heads), np.asarray(skeleton.tails)
    scale = max(float(np.linalg.norm(tails - heads, axis=1).max()), 1e-300)
    meets = np.linalg.norm(tails[:, None, :] - heads[None, :, :], axis=-1) <= 1e-9 * scale
    np.fill_diagonal(meets, False)                    # meets[p, c]: c starts at p's tail
    roots = np.flatnonzero(~meets.any(axis=0))
    if not roots.size:
        return None
    root = heads[roots[0]]
    starts = np.flatnonzero(np.linalg.norm(heads - root, axis=1) <= 1e-9 * scale)
    best: list[int] = []
    for start in starts:
        branch, todo = {int(start)}, [int(start)]
        while todo:
            for child in np.flatnonzero(meets[todo.pop()]):
                if int(child) not in branch:
                    branch.add(int(child))
                    todo.append(int(child))
        if len(branch) > len(best):
            best = sorted(branch)
    direction = tails[best].mean(axis=0) - root
    long_axis = np.asarray(long_axis, dtype=np.float64)
    along = float(direction @ long_axis)
    if abs(along) <= _ACROSS * np.linalg.norm(direction) * np.linalg.norm(long_axis):
        return None
    return long_axis if along > 0 else -long_axis


def picture_up(file_up: np.ndarray | None, skeleton, long_axis: np.ndarray
               ) -> tuple[np.ndarray, str]:
    """The pictures' up ``(3,)`` (unit) and where it came from (for the log): the file's
    up axis ``file_up`` (``Animation.up``), else :func:`rig_up`, else ``long_axis``."""
    if file_up is not None:
        up = np.asarray(file_up, dtype=np.float64)
        return up / np.linalg.norm(up), "the file's up axis"
    long_axis = np.asarray(long_axis, dtype=np.float64) / np.linalg.norm(long_axis)
    signed = rig_up(skeleton, long_axis)
    if signed is not None:
        return signed, "the body's long axis, from the rig's root to its largest branch"
    return long_axis, "the body's long axis (the file names no up axis)"


def most_strained_cells(rest: np.ndarray, cells: np.ndarray, pose: np.ndarray,
                        share: float = STRAINED_SHARE) -> np.ndarray:
    """Indices of the ``share`` of tetrahedra ``cells`` ``(T, 4)`` with the largest Green
    strain ``|F^T F - I|`` going from ``rest`` to ``pose`` (vertex positions ``(n, 3)``),
    at least one."""
    rest_corners = np.asarray(rest, dtype=np.float64)[cells]
    pose_corners = np.asarray(pose, dtype=np.float64)[cells]
    rest_edges = np.swapaxes(rest_corners[:, 1:] - rest_corners[:, :1], 1, 2)   # (T, 3, 3)
    pose_edges = np.swapaxes(pose_corners[:, 1:] - pose_corners[:, :1], 1, 2)
    gradient = pose_edges @ np.linalg.inv(rest_edges)
    strain = np.linalg.norm(np.swapaxes(gradient, 1, 2) @ gradient - np.eye(3), axis=(1, 2))
    count = max(1, int(round(share * len(cells))))
    return np.sort(np.argsort(-strain, kind="stable")[:count])
