"""Do the lights fit the frames? A check of a lights file's axes and order against the normals
it gives.

A lights file in another axis convention (y measured down the image rows, an azimuth of the
other sign) or with mirror-image lamps swapped gives normals that fit the frames exactly as
well: the least-squares residual cannot tell. The shape can. Mirroring the lights in x or y
mirrors the gradients, $(p, q) \\to (-p, q)$ or $(p, -q)$, and an integrable field
($\\partial p / \\partial y = \\partial q / \\partial x$) becomes one whose curl is twice either
derivative. So the share of curl in the gradients' derivatives tells the convention apart, with
no model of the object. Turning the lights by 180 degrees gives $(-p, -q)$, integrable again:
the same object, hollow. Its sign of curvature tells that one apart, for objects that bulge
toward the camera, as faces do. A lights file in another order than the frames (a quarter turn
of a scanner's lamps, frames sorted another way) is found by trying the other orders: one
whose curl is far lower, or (from four lights on) whose least-squares residual is far lower,
is the frames' order. The residual sees the orders the shape cannot (a centre lamp swapped
with an outer one), and cannot see those the shape can (mirror images): each is blind where
the other looks.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ._directions import validate_lights

__all__ = ["LightCheck", "check_lights"]

# The frames are block-averaged to about this many cells across the lit object before the
# normals are solved: the curl of pixel noise would otherwise swamp the object's.
_CELLS_ACROSS = 48
# Below this many 2x2 loops of cells the check gives no verdict.
_MIN_LOOPS = 50
# `curl` above which the lights are called mirrored (mirrored, they would give below 0.65):
# between the lights as given and mirrored on real captures (`benchmarks/light_check.py`,
# docs/robust.md "A lights file in the wrong convention or order").
MIRRORED_CURL = 1.35
# `convexity` above which the surface is called hollow.
HOLLOW_CONVEXITY = 0.1
# How much lower than the lights' own curl another order's must be to be called the frames'.
REORDER_MARGIN = 0.4
# How many times the lowest least-squares residual (the median over cells) of the orders tried
# the lights' own must be to be called in the wrong order: 1 + RESIDUAL_SLACK / (K - 3), for
# K - 3 residual degrees of freedom per cell (5 for four lights, 3 for five, 1.44 for twelve).
RESIDUAL_SLACK = 4.0
# Relative residuals below this (1e-4 RMS) are an exact fit, float32 rounding: their ratios
# would be noise.
_EXACT = 1e-8
# Up to this many lights every order is tried; above, each swap of two, each cyclic shift,
# the reversal, and the order of frame numbers sorted as text (1, 10, 11, 2, ...) both ways.
_ALL_ORDERS = 6


class LightCheck(NamedTuple):
    """What `check_lights` found.

    - `curl`: in [0, 2], the share of curl in the normals' gradient field,
      $\\sum (p_y - q_x)^2 / \\sum (p_y^2 + q_x^2)$ over loops of cells: 0 for an integrable
      field, about 1 for noise, 2 - c for the same lights mirrored in x or y. NaN when fewer
      than 50 loops could be measured.
    - `convexity`: in [-1, 1], $\\sum (p_x + q_y) / \\sum (|p_x| + |q_y|)$: negative for a surface
      that bulges toward the camera, positive for a hollow one. NaN as `curl`.
    - `mirrored`: `curl` > `MIRRORED_CURL` = 1.35: the lights mirrored in x or y fit the
      frames' shape better (a wrong sign of one axis, or mirror-image lamps swapped).
    - `reordered`: another order of the lights, `best_order`, fits the frames far better: its
      least-squares residual is lower by more than a factor `1 + RESIDUAL_SLACK / (K - 3)`
      (with at least four lights), or its curl is lower by more than `REORDER_MARGIN` = 0.4
      (and, when `mirrored`, as low as mirroring back would): the lights file lists the lamps
      in another order than the frames.
    - `best_order`: with `reordered`, the order: `lights[best_order]` fits the frames (frame
      k takes line `best_order[k]`); else None. It is the order of lowest curl among those
      whose residual is within that factor of the lowest; orders with the same curl (within
      0.02) are told apart by the most negative convexity.
    - `best_curl`: the curl of that order (NaN without a verdict).
    - `residual_ratio`: the lights' own least-squares residual (the median over the cells of
      $\\|i - L b\\|^2 / \\|i\\|^2$) over the lowest of the orders tried: 1 when no order fits
      better; NaN with three lights (every order fits exactly) or without a verdict.
    - `hollow`: `convexity` > 0.1, and neither `mirrored` nor `reordered`: the surface is
      hollow; for a face, the lights are turned by 180 degrees (x and y both negated).
    - `loops`: the number of 2x2 loops of cells measured.
    - `block`: the side in pixels of the cells the frames were averaged over.
    - `unchecked`: why there is no verdict (`curl` NaN), or "" when there is one.
    """

    curl: float
    convexity: float
    mirrored: bool
    reordered: bool
    best_order: tuple[int, ...] | None
    best_curl: float
    residual_ratio: float
    hollow: bool
    loops: int
    block: int
    unchecked: str

    @property
    def flagged(self) -> bool:
        return self.mirrored or self.reordered or self.hollow

    def summary(self) -> str:
        """One paragraph for a person: what was measured and, when flagged, what to check."""
        if self.unchecked:
            return f"lights: not checked against the frames: {self.unchecked}"
        said = (f"lights: curl {self.curl:.2f} of the normals' gradients (0 integrable, about 1 "
                f"noise), convexity {self.convexity:+.2f} (negative: bulging toward the camera)")
        if self.mirrored:
            said += (f". The same lights mirrored in x or y would give curl "
                     f"{2 - self.curl:.2f}: is the lights file mirrored? DESIGN.md's camera frame "
                     "has x right, y UP (not down the image rows), z toward the viewer; check the "
                     "sign of each axis, of the azimuths, and that left and right (or upper and "
                     "lower) lamps are not swapped")
        if self.reordered:
            residual = (f", least-squares residual {1 / self.residual_ratio:.2g} times the "
                        "lights' own" if self.residual_ratio > 1.05 else "")
            said += (f". The frames fit the lights in the order {list(self.best_order)} (frame k "
                     f"takes line best_order[k] of the lights) far better: curl "
                     f"{self.best_curl:.2f}{residual}. Are the lights listed in another order "
                     "than the frames (a turn of the lamps, a lamp moved to the other end of "
                     "the list, or frames sorted another way)?")
        elif self.hollow:
            said += (". The surface is hollow: if it should bulge toward the camera (a face "
                     "does), the lights are turned by 180 degrees (x and y both negated, or "
                     "opposite lamps swapped)")
        return said


def check_lights(
    images: Float[ArrayLike, "K H W *C"],
    lights: Float[ArrayLike, "K 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    max_zenith_deg: float = 50.0,
) -> LightCheck:
    """Check that `lights` are in the frames' axis convention and order, from the shape they
    give.

    Each frame (grey: the channel mean) is averaged over square blocks, about 48 across the lit
    part of `mask`, and the normals are solved by least squares; blocks whose normal leans more
    than 78 degrees from the view axis are left out. Over every 2x2 loop of blocks left, the
    gradients $p = -n_x/n_z$, $q = -n_y/n_z$ give `curl` and `convexity` (see `LightCheck`).

    The same is measured for the lights in other orders (every order up to 6 lights; above,
    each swap of two, each cyclic shift, the reversal and the order of names sorted as text),
    with each order's least-squares residual over the lit blocks, to find `best_order`.

    On the shared Yale B faces' five scanner frames, the lights as given gave curl 0.36-0.45
    and mirrored 1.55-1.64; 200 random sets of five of each face's lights within 50 degrees
    at most 1.10, and no other order of them had a curl lower by more than 0.17; psm's cat
    and owl 0.33 and 0.47 (mirrored 1.67, 1.53). Turned by 180 degrees, the faces' convexity
    went from -0.15..-0.21 to +0.15..+0.21. A quarter turn of the scanner's four outer lamps
    gave 1.16-1.22, and its best order the right lights. The residual ratio: 1.00 as given on
    every face and on psm's objects; at most 1.57 (five lights) and 3.50 (four) over the
    random sets within 50 degrees; 7.05-221 with two of the cross's lamps swapped that are
    not mirror images (the centre and an outer one, or two neighbours), four or five lights,
    or the centre lamp listed last. Not seen: most swaps of two of psm's twelve lamps less
    than 10 degrees apart (`benchmarks/light_check.py`, docs/robust.md "A lights file in the
    wrong convention or order").

    **Arguments:**
    - `images`: `(K, H, W)` or `(K, H, W, C)` frames, ambient subtracted, intensities
      equalised (as `load_capture` gives them).
    - `lights`: `(K, 3)` unit lights in the camera frame, as given.
    - `mask`: `(H, W)` bool, the object (default: every pixel; dark pixels are left out).
    - `max_zenith_deg`: no verdict when a light is further than this from the view axis.
      Such lights shadow much of a face, where the least-squares normals, and so their curl,
      are wrong: sets of five of all of Yale B's lights gave curls up to 1.26 and residual
      ratios up to 15 as given.

    **Returns:** a `LightCheck`.

    **Raises:** `ValueError` naming `images`, `lights` or `mask` when shapes disagree or the
    lights do not span 3-D.
    """
    if not 0 < max_zenith_deg <= 180:
        raise ValueError(f"max_zenith_deg must be in (0, 180], got {max_zenith_deg}")
    images = np.asarray(images, np.float32)
    if images.ndim not in (3, 4):
        raise ValueError(f"images must be (K, H, W) or (K, H, W, C), got shape {images.shape}")
    lights = validate_lights(lights).astype(np.float64)
    if len(lights) != len(images):
        raise ValueError(f"lights: {len(lights)} lights for {len(images)} frames (images)")
    grey = images if images.ndim == 3 else images.mean(axis=-1)
    h, w = grey.shape[1:]
    mask = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != (h, w):
        raise ValueError(f"mask must have shape (H, W) = {(h, w)}, got {mask.shape}")
    zenith = np.degrees(np.arccos(np.clip(lights[:, 2], -1, 1)))
    if zenith.max() > max_zenith_deg:
        return _unchecked(0, 1, f"light {int(zenith.argmax())} is {zenith.max():.0f} degrees "
                                f"from the view axis, more than max_zenith_deg="
                                f"{max_zenith_deg:g}")
    cells = _cells(grey, mask)
    if cells is None:
        return _unchecked(0, 1, "no lit pixel in the mask")
    g, keep, f = cells
    k = len(lights)
    orders = _orders(k)  # the lights as given first
    if k > 3:
        residual = np.maximum(_residuals(g, keep, lights[orders]), _EXACT)
        factor = 1 + RESIDUAL_SLACK / (k - 3)
        ratio = float(residual[0] / residual.min())
        fits = residual <= factor * residual.min()  # the frames' order is among these
    else:  # three lights fit any frames exactly, in any order
        factor, ratio, fits = np.inf, np.nan, np.ones(len(orders), bool)
    # The shape only of the orders that fit, and of the lights as given (for the synthetic
    # scanner's five lamps, 8 of the 120 orders span the same space: its mirror images and turns).
    shape = np.flatnonzero(fits | (np.arange(len(orders)) == 0))
    curl, convexity, loops = (np.full(len(orders), v) for v in (np.inf, np.inf, 0))
    curl[shape], convexity[shape], loops[shape] = _shape(g, keep, lights[orders[shape]])
    if loops[0] < _MIN_LOOPS:
        return _unchecked(int(loops[0]), f, f"{loops[0]} loops of {f}-pixel cells lit and "
                                            f"facing the camera, need {_MIN_LOOPS}")
    tried = np.where((loops >= _MIN_LOOPS) & fits, curl, np.inf)
    if not np.isfinite(tried.min()):  # no order that fits leaves enough loops: judge them all
        tried = np.where(fits, curl, np.inf)
    ties = np.flatnonzero(tried <= tried.min() + 0.02)
    best = ties[np.argmin(convexity[ties])]  # of equal curls, the bulging one
    if ratio > factor:  # not the frames' order: the mirror is judged in the order found
        mirrored, reordered = bool(tried[best] > MIRRORED_CURL), True
    else:
        mirrored = bool(curl[0] > MIRRORED_CURL)
        # Mirrored lights are only also reordered when an order undoes the mirror as well as
        # mirroring them back would (a scanner's cross: swapping left and right is a mirror).
        reordered = bool(tried[best] < curl[0] - REORDER_MARGIN
                         and (not mirrored or tried[best] <= 2 - curl[0] + 0.02))
    return LightCheck(
        curl=float(curl[0]), convexity=float(convexity[0]), mirrored=mirrored,
        reordered=reordered,
        best_order=tuple(int(i) for i in orders[best]) if reordered else None,
        best_curl=float(tried[best]), residual_ratio=ratio,
        hollow=bool(not (mirrored or reordered) and convexity[0] > HOLLOW_CONVEXITY),
        loops=int(loops[0]), block=f, unchecked="")


def _orders(k):
    """`(P, k)` orders of k lights to try, the identity first: every order up to
    `_ALL_ORDERS` lights; above, each swap of two, each cyclic shift, the reversal, and the
    order of the numbers 0..k-1 sorted as text and its inverse."""
    if k <= _ALL_ORDERS:
        return np.array(list(itertools.permutations(range(k))))
    same = np.arange(k)
    swaps = []
    for i, j in itertools.combinations(range(k), 2):
        swaps.append(same.copy())
        swaps[-1][[i, j]] = [j, i]
    text = np.array(sorted(range(k), key=str))
    return np.array([same, *swaps, *(np.roll(same, s) for s in range(1, k)), same[::-1],
                     text, np.argsort(text)])


def _cells(grey, mask):
    """`(g, keep, f)`: the `(K, H, W)` frames `grey` averaged over `f` x `f` blocks, about
    `_CELLS_ACROSS` across the lit part of `mask`, and which blocks have every pixel lit (in
    the mean frame, above a tenth of its 99th percentile in the mask); None when no pixel of
    `mask` is lit. The level and the extent are found on every 4th row and column."""
    sub, sub_mask = grey[:, ::4, ::4].mean(axis=0), mask[::4, ::4]
    level = 0.1 * np.nanpercentile(sub[sub_mask], 99) if sub_mask.any() else np.nan
    rows, cols = np.nonzero(sub_mask & (sub > level))
    if not len(rows):
        return None
    side = 4 * int(max(rows.max() - rows.min(), cols.max() - cols.min())) + 4
    f = max(1, round(side / _CELLS_ACROSS))
    lit = mask & (grey.mean(axis=0) > level)
    return _blocks(grey, f), _blocks(lit[None].astype(np.float32), f)[0] == 1, f


def _residuals(g, keep, lights, average=np.median):
    """`(P,)`: the median over the `keep` blocks of `g` `(K, h, w)` of the least-squares fit's
    relative residual $\\|i - L b\\|^2 / \\|i\\|^2$ under each of the `(P, K, 3)` light
    sets (`average=np.mean`: the mean, which `benchmarks/light_check.py` compares). The
    median, not the mean: the shadows and highlights of a few blocks would otherwise decide
    (docs/robust.md, "A lights file in the wrong convention or order")."""
    if not keep.any():
        return np.zeros(len(lights))
    lit = g[:, keep].astype(np.float32)
    # (I - L L^+) i: the part of each cell's samples that no normal under these lights explains
    project = np.eye(len(g)) - lights @ np.linalg.pinv(lights)
    fit = np.matmul(project.astype(np.float32), lit)
    return average((fit ** 2).sum(axis=1) / np.maximum((lit ** 2).sum(axis=0), 1e-30), axis=1)


def _shape(g, keep, lights):
    """`(curl, convexity, loops)`, each `(P,)`: the least-squares normals of the `(K, h, w)`
    blocks `g` under each of the `(P, K, 3)` light sets, measured over the 2x2 loops of `keep`
    blocks whose normal leans less than 78 degrees from the view axis."""
    k, h, w = g.shape
    b = np.matmul(np.linalg.pinv(lights).astype(np.float32),
                  g.reshape(k, h * w).astype(np.float32)).reshape(-1, 3, h, w)
    keep = keep & (b[:, 2] > 0.2 * np.linalg.norm(b, axis=1))  # |p|, |q| <= 4.9
    nz = np.where(keep, b[:, 2], 1)
    p, q = np.where(keep, -b[:, 0] / nz, 0), np.where(keep, -b[:, 1] / nz, 0)
    # Derivatives at the centre of each 2x2 loop; y is up, so a row down is -1 in y.
    dx = lambda a: 0.5 * (a[:, 1:, 1:] - a[:, 1:, :-1] + a[:, :-1, 1:] - a[:, :-1, :-1])
    dy = lambda a: -0.5 * (a[:, 1:, 1:] - a[:, :-1, 1:] + a[:, 1:, :-1] - a[:, :-1, :-1])
    loop = keep[:, 1:, 1:] & keep[:, :-1, 1:] & keep[:, 1:, :-1] & keep[:, :-1, :-1]
    total = lambda a: np.where(loop, a, 0).sum(axis=(1, 2))
    py, qx, px, qy = dy(p), dx(q), dx(p), dy(q)
    curl = total((py - qx) ** 2) / np.maximum(total(py ** 2 + qx ** 2), 1e-30)
    convexity = total(px + qy) / np.maximum(total(np.abs(px) + np.abs(qy)), 1e-30)
    return curl, convexity, loop.sum(axis=(1, 2))


def _unchecked(loops, block, why):
    return LightCheck(curl=np.nan, convexity=np.nan, mirrored=False, reordered=False,
                      best_order=None, best_curl=np.nan, residual_ratio=np.nan, hollow=False,
                      loops=loops, block=block, unchecked=why)


def _blocks(stack, f):
    """`(K, H, W)` averaged over `f` x `f` blocks (the ragged last rows and columns dropped)."""
    if f == 1:
        return stack
    k, h, w = stack.shape
    h, w = h // f * f, w // f * f
    return stack[:, :h, :w].reshape(k, h // f, f, w // f, f).mean(axis=(2, 4))
