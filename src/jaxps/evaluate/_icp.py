"""Rigid (optionally similarity) ICP between a reconstruction and a ground-truth scan.

Iterative closest point: Besl & McKay, "A method for registration of 3-D shapes", IEEE TPAMI
14(2), 1992 (point-to-point); Chen & Medioni, "Object modelling by registration of multiple range
images", Image and Vision Computing 10(3), 1992 (point-to-plane). Each step pairs every source
point with its nearest target point, drops the worst pairs (trimmed ICP: Chetverikov et al.,
ICPR 2002) and solves for the increment of $x \\mapsto s R x + t$:

- point-to-point: the weighted closed form of Umeyama, "Least-squares estimation of
  transformation parameters between two point patterns", IEEE TPAMI 13(4), 1991 (Kabsch with a
  reflection guard, plus the optimal scale when `scale=True`);
- point-to-plane: $\\min \\sum_i w_i ((s R p_i + t - q_i) \\cdot n_i)^2$ linearised in a small
  rotation $\\omega$, scale $\\delta$ and translation, a 6x6 (7x7 with scale) normal-equation
  solve; the rotation increment is then made exact with Rodrigues' formula.

Nearest neighbours come from `scipy.spatial.cKDTree`, built once on the (fixed) target and queried
each step: O(N log M) per step, where a jitted brute-force search is O(N M) (1.6e9 distance
evaluations per step for two 40k-point DiLiGenT clouds, seconds on two cores against ~20 ms).
The loop therefore runs on the host with an explicit `max_steps`; the per-step solves are jitted.
OpenCV's `ppf_match_3d_ICP` (contrib) is as accurate on DiLiGenT but rigid only (a height map in
pixel units needs a scale), wants normals on both clouds, reports no per-point distances or
convergence, and ran 5-15x slower (`benchmarks/bench_icp.py`), so it is the benchmark's baseline.

Point clouds are `(N, 3)` in the camera frame of DESIGN.md (x right, y up, z toward the viewer).
`points_from_height` and `points_from_depth` turn a height map or a perspective depth map into
that layout.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

__all__ = [
    "ICPResult",
    "ICP_METHODS",
    "estimate_normals",
    "icp",
    "points_from_depth",
    "points_from_height",
    "transform_points",
]

ICP_METHODS: tuple[str, ...] = ("point_to_point", "point_to_plane")
# With `scale=True`, ICP stops (not converged) once the scale has fallen below this fraction of
# the ratio of the clouds' spreads: the source has collapsed toward a point of the target,
# which it then "fits" to round-off. Seen from wrong starting orientations (a scan stored with
# its axes turned), where the scale fell by orders of magnitude.
_COLLAPSED = 1e-2


class ICPResult(NamedTuple):
    """The similarity transform that maps the source onto the target: $x \\mapsto s R x + t$.

    - `rotation`: `(3, 3)` proper rotation (det +1).
    - `translation`: `(3,)`.
    - `scale`: scalar, 1 unless `icp(..., scale=True)`.
    - `aligned`: `(N, 3)` the source after the transform.
    - `distances`: `(N,)` distance from each aligned source point to its nearest target point.
    - `inliers`: `(N,)` bool, the pairs kept by the last step (trim / `max_distance`).
    - `rms`: RMS of `distances` over `inliers` (the quantity ICP minimises, point-to-point).
    - `steps`: steps taken; `converged`: whether the relative change of the error fell below
      `tol` before `max_steps` (False also when a scaled fit collapsed: `icp`).
    """

    rotation: Float[np.ndarray, "3 3"]
    translation: Float[np.ndarray, "3"]
    scale: float
    aligned: Float[np.ndarray, "N 3"]
    distances: Float[np.ndarray, " N"]
    inliers: Bool[np.ndarray, " N"]
    rms: float
    steps: int
    converged: bool


def _check_points(points, name: str) -> np.ndarray:
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3) points, got shape {arr.shape}")
    if arr.shape[0] < 3:
        raise ValueError(f"{name} needs at least 3 points, got {arr.shape[0]}")
    if not np.issubdtype(arr.dtype, np.floating):
        arr = arr.astype(np.float32)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has NaN/Inf coordinates: drop them (e.g. with a mask) first")
    return arr


def _spread_ratio(source, target) -> float:
    """The target's RMS distance from its centroid over the source's: the scale that makes the
    two clouds equally large (`icp`'s start with `init="centroid"` and `scale=True`)."""
    src, tgt = (np.asarray(a, np.float64) for a in (source, target))
    spread_s = np.sqrt(np.mean(np.sum((src - src.mean(axis=0)) ** 2, axis=-1)))
    spread_t = np.sqrt(np.mean(np.sum((tgt - tgt.mean(axis=0)) ** 2, axis=-1)))
    return float(spread_t / max(spread_s, np.finfo(np.float64).tiny))


def points_from_height(
    height: Float[ArrayLike, "H W"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    pixel_size: float = 1.0,
) -> tuple[Float[np.ndarray, "N 3"], Int[np.ndarray, "N 2"]]:
    """Points of an orthographic height map: x right and y up from the image centre, z = height.

    **Arguments:**
    - `height`: `(H, W)` height toward the viewer (e.g. from `jaxps.integrate`).
    - `mask`: `(H, W)` bool, pixels to keep (default: every finite pixel).
    - `pixel_size`: the size of a pixel in the height's unit.

    **Returns:** `(points (N, 3), pixels (N, 2))`, `pixels` holding each point's `(row, col)`,
    points in the floating dtype of `height`.
    """
    z = np.asarray(height)
    if z.ndim != 2:
        raise ValueError(f"height must be (H, W), got shape {z.shape}")
    if not np.issubdtype(z.dtype, np.floating):
        z = z.astype(np.float32)
    keep = np.isfinite(z)
    if mask is not None:
        if np.shape(mask) != z.shape:
            raise ValueError(f"mask must have shape {z.shape}, got {np.shape(mask)}")
        keep &= np.asarray(mask, bool)
    rows, cols = np.nonzero(keep)
    h, w = z.shape
    x = (cols - (w - 1) / 2) * pixel_size
    y = ((h - 1) / 2 - rows) * pixel_size
    pts = np.stack([x, y, z[rows, cols]], axis=-1).astype(z.dtype)
    return pts, np.stack([rows, cols], axis=-1)


def points_from_depth(
    depth: Float[ArrayLike, "H W"],
    intrinsics: Float[ArrayLike, "3 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
) -> tuple[Float[np.ndarray, "N 3"], Int[np.ndarray, "N 2"]]:
    """Back-project a perspective depth map (distance along the optical axis) into 3-D.

    With intrinsics $K$ (OpenCV layout: focal lengths $f_x, f_y$, principal point $c_x, c_y$,
    rows growing downward), pixel $(u, v)$ at depth $d$ goes to
    $(x, y, z) = ((u - c_x) d / f_x,\\ -(v - c_y) d / f_y,\\ -d)$: the DESIGN.md camera frame,
    camera at the origin looking down $-z$.

    **Arguments:**
    - `depth`: `(H, W)` positive depth (e.g. DiLiGenT `depth_gt`, millimetres); NaN = no data.
    - `intrinsics`: `(3, 3)` camera matrix (e.g. DiLiGenT `K.txt`).
    - `mask`: `(H, W)` bool, pixels to keep (default: every finite, positive depth).

    **Returns:** `(points (N, 3), pixels (N, 2))` as in `points_from_height`.
    """
    d = np.asarray(depth)
    k = np.asarray(intrinsics, np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {d.shape}")
    if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise ValueError(f"intrinsics must be a finite (3, 3) camera matrix, got {k!r}")
    if not np.issubdtype(d.dtype, np.floating):
        d = d.astype(np.float32)
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(d) & (d > 0)
    if mask is not None:
        if np.shape(mask) != d.shape:
            raise ValueError(f"mask must have shape {d.shape}, got {np.shape(mask)}")
        keep &= np.asarray(mask, bool)
    rows, cols = np.nonzero(keep)
    dd = d[rows, cols].astype(np.float64)
    x = (cols - k[0, 2]) * dd / k[0, 0]
    y = -(rows - k[1, 2]) * dd / k[1, 1]
    pts = np.stack([x, y, -dd], axis=-1).astype(d.dtype)
    return pts, np.stack([rows, cols], axis=-1)


def estimate_normals(
    points: Float[ArrayLike, "N 3"], *, neighbours: int = 10, tree: cKDTree | None = None
) -> Float[np.ndarray, "N 3"]:
    """Unit normals of a point cloud from the smallest principal axis of each point's neighbours.

    Oriented toward the viewer of DESIGN.md ($n_z \\ge 0$), which suits height maps and scans
    taken from the camera. `neighbours`: how many nearest points, the point itself included,
    each plane is fitted to (at least 3; a cloud of fewer points uses them all). `tree` may
    pass a prebuilt `cKDTree` of `points`.

    **Returns:** `(N, 3)` unit normals in the dtype of `points`.
    """
    pts = _check_points(points, "points")
    if not (isinstance(neighbours, (int, np.integer)) and neighbours >= 3):
        raise ValueError(f"neighbours must be an int >= 3 (a plane needs three points), got "
                         f"{neighbours!r}")
    k = int(min(neighbours, pts.shape[0]))
    from scipy.spatial import cKDTree  # SciPy loads when first used

    tree = cKDTree(pts) if tree is None else tree
    _, idx = tree.query(pts, k=k)
    nb = pts[idx].astype(np.float64)  # (N, k, 3)
    nb -= nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, vecs = np.linalg.eigh(cov)
    n = vecs[:, :, 0]
    n = np.where(n[:, 2:3] < 0, -n, n)
    return n.astype(pts.dtype)


def _rodrigues(w):
    theta = jnp.linalg.norm(w)
    safe = jnp.where(theta > 0, theta, 1)
    k = w / safe
    kx = jnp.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], w.dtype)
    eye = jnp.eye(3, dtype=w.dtype)
    r = eye + jnp.sin(theta) * kx + (1 - jnp.cos(theta)) * (kx @ kx)
    return jnp.where(theta > 0, r, eye)


@functools.partial(jax.jit, static_argnames="with_scale")
def _step_point_to_point(p, q, w, *, with_scale):
    """Weighted Umeyama: the similarity (s, R, t) minimising sum w |s R p + t - q|^2."""
    wsum = jnp.maximum(jnp.sum(w), jnp.finfo(p.dtype).tiny)
    mp = (w @ p) / wsum
    mq = (w @ q) / wsum
    pc, qc = p - mp[None, :], q - mq[None, :]
    cov = (qc * w[:, None]).T @ pc / wsum  # (3, 3) target x source
    u, sv, vt = jnp.linalg.svd(cov)
    sign = jnp.sign(jnp.linalg.det(u) * jnp.linalg.det(vt))
    d = jnp.stack([jnp.ones((), p.dtype), jnp.ones((), p.dtype), jnp.where(sign < 0, -1, 1)
                   .astype(p.dtype)])
    r = (u * d[None, :]) @ vt
    if with_scale:
        var_p = jnp.sum(w * jnp.sum(pc**2, axis=-1)) / wsum
        s = jnp.sum(sv * d) / jnp.maximum(var_p, jnp.finfo(p.dtype).tiny)
    else:
        s = jnp.ones((), p.dtype)
    t = mq - s * (r @ mp)
    return s, r, t


@functools.partial(jax.jit, static_argnames="with_scale")
def _step_point_to_plane(p, q, nq, w, *, with_scale):
    """Linearised point-to-plane step about the weighted target centroid (Chen & Medioni)."""
    wsum = jnp.maximum(jnp.sum(w), jnp.finfo(p.dtype).tiny)
    c = (w @ q) / wsum
    pc, qc = p - c[None, :], q - c[None, :]
    cols = [jnp.cross(pc, nq)]
    if with_scale:
        cols.append(jnp.sum(pc * nq, axis=-1, keepdims=True))
    cols.append(nq)
    a = jnp.concatenate(cols, axis=-1)  # (N, 6 or 7)
    b = -jnp.sum((pc - qc) * nq, axis=-1)
    ata = (a * w[:, None]).T @ a
    atb = (a * w[:, None]).T @ b
    # A tiny ridge keeps a degenerate geometry (a plane: rotation about its normal is free)
    # finite; it only moves parameters the data do not constrain.
    ridge = 1e-9 * jnp.trace(ata) / ata.shape[0] + jnp.finfo(p.dtype).tiny
    x = jnp.linalg.solve(ata + ridge * jnp.eye(ata.shape[0], dtype=p.dtype), atb)
    r = _rodrigues(x[:3])
    s = 1 + x[3] if with_scale else jnp.ones((), p.dtype)
    tc = x[-3:]
    # p -> s R (p - c) + c + tc
    t = c + tc - s * (r @ c)
    return s, r, t


def transform_points(
    points: Float[ArrayLike, "N 3"], result: ICPResult
) -> Float[np.ndarray, "N 3"]:
    """Apply an `ICPResult`'s transform $x \\mapsto s R x + t$ to other `(N, 3)` points."""
    pts = _check_points(points, "points")
    out = result.scale * pts.astype(np.float64) @ np.asarray(result.rotation, np.float64).T
    return (out + np.asarray(result.translation, np.float64)).astype(pts.dtype)


def icp(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "M 3"],
    *,
    method: str = "point_to_plane",
    scale: bool = False,
    max_steps: int = 50,
    tol: float = 1e-5,
    trim: float = 1.0,
    max_distance: float | None = None,
    init: str = "identity",
    target_normals: Float[ArrayLike, "M 3"] | None = None,
) -> ICPResult:
    """Align `source` to `target` with iterative closest point; return the transform.

    Each step pairs every aligned source point with its nearest target point (`cKDTree`),
    keeps the `trim` fraction of closest pairs that are also within `max_distance`, and
    solves for the similarity increment (module docstring). It stops when the RMS pair
    distance changes by less than `tol` (relative) between steps or reaches float32 round-off of
    the target's size (an exact fit), or after `max_steps` (then `converged` is False).

    ICP is local: it converges to the right answer from a misalignment of a few degrees and a
    fraction of the object's size. `init="centroid"` first moves the source's centroid onto
    the target's (and, with `scale=True`, matches their RMS spread), which brings a height map
    in pixel units near a scan in millimetres. With `scale=True` it stops, not converged, when
    the scale falls below 1/100 of the ratio of the clouds' spreads: from a poor start
    (such as a scan whose axes are turned) the source can shrink onto a point of the target,
    which it then fits to round-off. A step changes the scale by a factor of 1/2 to 2 at most.

    **Arguments:**
    - `source`: `(N, 3)` points to move (e.g. `points_from_height` of a reconstruction).
    - `target`: `(M, 3)` fixed points (e.g. `points_from_depth` of the ground-truth scan).
    - `method`: `"point_to_plane"` (default; fewer steps on smooth surfaces) or
      `"point_to_point"`.
    - `scale`: also fit a global scale (a height map in pixel units against a scan in mm).
    - `max_steps`: the step limit.
    - `tol`: relative change of the RMS pair distance that counts as converged.
    - `trim`: fraction in (0, 1] of the closest pairs used each step (1 = all).
    - `max_distance`: pairs farther apart than this are dropped (default: none).
    - `init`: `"identity"` or `"centroid"`.
    - `target_normals`: `(M, 3)` normals for point-to-plane (default: `estimate_normals`).

    **Returns:** an `ICPResult` (rotation, translation, scale, aligned source, per-point
    distances, inliers, RMS, steps, converged) in the floating dtype of `source`.
    """
    src = _check_points(source, "source")
    tgt = _check_points(target, "target")
    if method not in ICP_METHODS:
        raise ValueError(f"method must be one of {ICP_METHODS}, got {method!r}")
    if init not in ("identity", "centroid"):
        raise ValueError(f"init must be 'identity' or 'centroid', got {init!r}")
    if not (0 < trim <= 1):
        raise ValueError(f"trim must be in (0, 1], got {trim}")
    if int(max_steps) < 1:
        raise ValueError(f"max_steps must be at least 1, got {max_steps}")
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be finite and >= 0, got {tol}")
    if max_distance is not None and not max_distance > 0:
        raise ValueError(f"max_distance must be positive, got {max_distance}")
    for name, pts in (("source", src), ("target", tgt)):
        centred = pts - pts.mean(axis=0, dtype=np.float64)
        spread = np.linalg.eigvalsh(centred.T @ centred)  # ascending
        if not spread[1] > 1e-12 * spread[2]:  # NaN transforms, then scipy's "'x' must be finite"
            raise ValueError(f"{name} points lie on one line (or at one point): no rigid "
                             f"transform onto them is determined")
    dtype = src.dtype
    from scipy.spatial import cKDTree

    tree = cKDTree(tgt)
    if method == "point_to_plane":
        if target_normals is None:
            nrm = estimate_normals(tgt, tree=tree)
        else:
            nrm = _check_points(target_normals, "target_normals")
            if nrm.shape != tgt.shape:
                raise ValueError(
                    f"target_normals must have the shape of target {tgt.shape}, got {nrm.shape}")
        nrm_j = jnp.asarray(nrm, jnp.float32)

    # The transform is kept in float64 on the host; each step is solved in float32 on points
    # centred on the target's centroid (DiLiGenT depths are ~1500 mm from the camera).
    origin = tgt.astype(np.float64).mean(axis=0)
    src64 = src.astype(np.float64)
    tgt_j = jnp.asarray(tgt.astype(np.float64) - origin, jnp.float32)
    s, rot, t = 1.0, np.eye(3), np.zeros(3)
    matched = _spread_ratio(src64, tgt) if scale else 0.0
    if init == "centroid":
        s = matched if scale else 1.0
        t = tgt.astype(np.float64).mean(axis=0) - s * src64.mean(axis=0)

    n_keep = max(3, int(np.ceil(trim * src.shape[0])))

    def pairs(s, rot, t):
        moved = s * src64 @ rot.T + t
        dist, idx = tree.query(moved)
        keep = np.ones(dist.shape, bool)
        if n_keep < dist.size:
            keep[np.argpartition(dist, n_keep - 1)[n_keep:]] = False
        if max_distance is not None:
            keep &= dist <= max_distance
        rms = float(np.sqrt(np.mean(dist[keep] ** 2))) if keep.sum() >= 3 else float("inf")
        return moved, dist, idx, keep, rms

    # An RMS at float32 round-off of the target's size is an exact fit: nothing left to gain.
    spread = float(np.sqrt(np.mean(np.sum((tgt - tgt.mean(axis=0)) ** 2, axis=-1))))
    floor = 16 * float(np.finfo(np.float32).eps) * spread
    prev = np.inf
    converged = False
    steps = 0
    while True:
        moved, dist, idx, keep, rms = pairs(s, rot, t)
        if not np.isfinite(rms) or s < _COLLAPSED * matched:
            break  # a source shrunk onto a point of the target fits it "exactly": no answer
        if rms <= floor or abs(prev - rms) <= tol * rms:
            converged = True
            break
        if steps == int(max_steps):
            break
        prev = rms
        p = jnp.asarray(moved - origin, jnp.float32)
        q = tgt_j[idx]
        w = jnp.asarray(keep, jnp.float32)
        if method == "point_to_point":
            ds, dr, dt = _step_point_to_point(p, q, w, with_scale=scale)
        else:
            ds, dr, dt = _step_point_to_plane(p, q, nrm_j[idx], w, with_scale=scale)
        # A step may at most halve or double the scale: the linearised scale 1 + delta can
        # otherwise turn negative on a poor pairing.
        ds = float(np.clip(ds, 0.5, 2.0))
        dr, dt = np.asarray(dr, np.float64), np.asarray(dt, np.float64)
        # Steps act on centred points: x -> ds dr (x - o) + o + dt.
        dt = dt + origin - ds * dr @ origin
        s, rot, t = ds * s, dr @ rot, ds * dr @ t + dt
        steps += 1

    return ICPResult(
        rotation=rot.astype(dtype),
        translation=t.astype(dtype),
        scale=float(s),
        aligned=moved.astype(dtype),
        distances=dist.astype(dtype),
        inliers=keep,
        rms=rms,
        steps=steps,
        converged=converged,
    )
