"""Hypothesis verification: is a posed model what the sensor saw, from the sensor's own viewpoint?

After Aldoma et al., "A global hypotheses verification method for 3D object recognition" (ECCV
2012), the step PCL's recognition pipeline ends with. The scene is the whole frame (table and
all) as a depth map; each hypothesis is its model posed in the camera frame. Of the model points
the camera would see (facing it, not behind the model's own nearer surface), each lands on a
pixel with a measured depth d and is

- an inlier: within ``tolerance(z)`` of the measured surface around that pixel;
- a violation: in front of it by more than that (the sensor saw through where the object would
  be: strong evidence against, whatever the cluster looked like);
- occluded: behind it (something stands in front; neutral);
- unmeasured: no depth there (neutral).

``fitness`` = inliers / (inliers + violations) is how much of what the sensor could judge agrees;
``support`` = inliers / visible is how much of the visible model is actually seen; judged among
accepted hypotheses (``Explained.support``), pixels an accepted object hides leave ``visible``.

The model's own side: a model that is one captured view is an open surface. Posed so that the
camera looks at the side the capture did not see, the model's nearest surface on most pixels faces
away, and its few facing points (a rim) would be judged on a handful of pixels. ``facing_share``
is the share of the pixels where the model's nearest surface faces the camera: a closed surface's
always does, bar its silhouette's edge; the same rule keeps a captured view's viewpoints
(``recognition.models``: a partial scan seen from behind is not a view).

Colour, where both the frame and the model have it: within depth noise a box or a cylinder of
about the model's size fits its surface (a can's 12 cm silhouette at a box's diagonal), but not its
colour. ``colour_agreement`` is the share of the inlier pixels whose rg-chromaticity (r, g over
r + g + b: brightness and shading divide out) lies within a tolerance of the colours of the model
around the point there (``chroma_ranges``: a pose a few millimetres off puts the other side of a
printed edge on the pixel); pixels too dark for a chromaticity are not judged.

Shape: every inlier lies within the tolerance, which has to allow for a pose a little off; a
surface of another shape can stay inside it (a can laid along a box's edge, its arc against the
two faces). Once the shift and tilt a small pose error makes are taken out, the residual of a right
hypothesis is the sensor's noise; ``shape_error`` is how far its spread goes beyond that, in the
noise's sigmas at the object's depth.

The outline: the ring of pixels just outside the model's silhouette (``OUTLINE_PX``). An object
ends there: beyond it the sensor sees background, a support it stands on, or something in front.
A ring pixel where the measured surface continues the model's own (it lies on the tangent plane of
the nearest model point, within the tolerance, normals within ``SAME_SURFACE_DEG``) says the model
was fitted onto part of a larger surface: Aldoma et al.'s clutter term. ``clutter`` is the share of the
measured ring that continues; ``outline_seen`` the share of the ring measured at all (where most of
the outline has no depth, nothing says the object ends there). Where the model's edge curves away
(a can's side) its tangent plane runs along the line of sight and nothing continues it: ``flush``
is the share of the measured ring at the depth of the model point beside it, the support the
object stands on left out, where the sensor sees no step at all.

A hypothesis is kept when these reach their thresholds (``recognition.config``, measured in
``benchmarks.recognition``); among kept ones a scene pixel explains at most one object
(``Explained``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from recognition.cloud import radius_neighbours

#: The virtual camera unorganised clouds are projected with: a 640x480 Kinect's intrinsics at half
#: resolution (a pixel is ~4 mm at 1 m). Organised clouds keep their own grid.
VIRTUAL_K = np.array([[262.5, 0.0, 159.75], [0.0, 262.5, 119.75], [0.0, 0.0, 1.0]])
VIRTUAL_SIZE = (240, 320)
#: Model points further than this behind the model's nearest point on their coarse cell are hidden
#: by the model itself (m); the coarse cell is this many pixels wide.
SELF_OCCLUSION_M, SELF_CELL_PX = 0.01, 4
#: The outline ring: pixels more than OUTLINE_PX[0] and at most OUTLINE_PX[1] (virtual-camera
#: pixels, ~4 mm at 1 m) outside the silhouette. The gap keeps the silhouette's own ragged edge out.
OUTLINE_PX = (2, 6)
#: A ring pixel continues the model's surface when its normal is within this of the model's there.
SAME_SURFACE_DEG = 30.0
#: Normals from depth differences this many pixels either side (a Kinect's depth noise at 2 m, ~7 mm,
#: would swamp neighbouring pixels' 8 mm spacing).
NORMAL_STEP_PX = 2
#: A cluster holding at least this share of a hypothesis's inlier pixels is a surface it explains
#: (``hidden_apart``); a cluster with fewer is what hides it, onto which inliers at its edge spill.
OWN_CLUSTER_SHARE = 0.25
#: Colours darker than this (r + g + b, each 0-1) have no usable chromaticity: 8-bit noise of a few
#: levels would move it by more than the tolerance.
MIN_BRIGHTNESS = 0.25
#: Fewer judged pixels than this say nothing about colour (``Verdict.colour_agreement`` is then 1).
MIN_COLOUR_PIXELS = 20
#: The residual's spread a model's own error leaves at any range (m): a mesh or a scan is not
#: the object to the millimetre. Beyond it the spread is judged in the sensor's depth noise.
SPREAD_FLOOR_M = 0.001
#: Fewer inlier pixels than this say nothing about shape (``Verdict.shape_error`` is then 0).
MIN_SHAPE_PIXELS = 20
#: The rg-chromaticity of grey, white and black: r = g = b.
GREY = 1.0 / 3.0
#: A model point's colour is every colour of the model within this of it (m): poses are a few mm
#: off, and on a printed surface that moves a pixel across an edge of the print.
COLOUR_RADIUS_M = 0.01


@dataclass(frozen=True)
class DepthView:
    """The scene as the sensor saw it: per pixel the nearest and farthest measured depth (m) in a
    3x3 neighbourhood (NaN: no return there), the projection K (3, 3) and the image size (H, W)."""

    near: np.ndarray
    far: np.ndarray
    K: np.ndarray
    z: np.ndarray  # (H, W) the measured depth itself (m, NaN: none)
    chroma: np.ndarray | None = None  # (H, W, 2) rg-chromaticity (NaN: too dark); None: no colour

    @classmethod
    def of(cls, cloud: np.ndarray, rgb: np.ndarray | None = None) -> DepthView:
        """From a camera-frame cloud: (H, W, 3) organised (every other row and column of its own
        grid, with the K its points fit) or (N, 3), projected with ``VIRTUAL_K``.

        rgb: the colour of each point, registered to the cloud ((H, W, 3) or (N, 3), uint8), if
        the sensor sent it."""
        pts = np.asarray(cloud)
        if rgb is not None and np.shape(rgb) != pts.shape:
            raise ValueError(f"colour {np.shape(rgb)} does not match the cloud {pts.shape}: one rgb8 triple per point")
        colour = None if rgb is None else np.asarray(rgb)
        if pts.ndim == 3 and min(pts.shape[:2]) == 1:  # a PCD with HEIGHT 1 is a list of points, not an image
            pts = pts.reshape(-1, 3)
            colour = None if colour is None else colour.reshape(-1, 3)
        if pts.ndim == 3:  # every other row and column: the virtual camera's resolution
            grid = pts[::2, ::2].astype(np.float64)
            z = grid[..., 2].copy()
            z[~np.isfinite(z) | (z <= 0)] = np.nan
            K = fit_intrinsics(grid)
            if colour is not None:  # the grid's pixels only, before converting a frame's worth of them
                colour = colour[::2, ::2].astype(np.float32) / 255.0
        else:
            K = VIRTUAL_K
            z, nearest = virtual_image(pts)
            if colour is not None:  # each pixel's colour is its nearest point's
                grid_colour = np.full((*z.shape, 3), np.nan, np.float32)
                shown = nearest >= 0
                grid_colour[shown] = colour.reshape(-1, 3)[nearest[shown]].astype(np.float32) / 255.0
                colour = grid_colour
        chroma = None if colour is None else chromaticity(colour)
        return cls(_filter3(z, nearest=True), _filter3(z, nearest=False), K, z, chroma)


@dataclass(frozen=True)
class Verdict:
    """How a posed model agrees with the depth view: pixel counts of its visible points."""

    visible: int
    inliers: int
    violations: int
    occluded: int
    pixels: (
        np.ndarray
    )  # flat indices of the inlier pixels, closed over the gaps between model points (for ``Explained``)
    outline: int = 0  # ring pixels around the silhouette, inside the image
    outline_measured: int = 0  # ... with a depth
    outline_continuing: int = 0  # ... where the model's surface goes on
    outline_flush: int = 0  # ... at the depth of the model's edge beside it, off the support: no step there
    inside_support: int = 0  # visible pixels hidden by a support plane the model point lies behind
    hidden: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # flat indices of the occluded pixels
    colour_judged: int = 0  # inlier pixels where both scene and model have a chromaticity
    colour_agreeing: int = 0  # ... within the colour tolerance of each other
    colour_distinct: int = 0  # judged pixels where the model's colour is no grey (``distinct_from_grey``) ...
    colour_distinct_agreeing: int = 0  # ... and of those, agreeing
    shape_error: float = 0.0  # the residual's spread beyond SPREAD_FLOOR_M, in depth-noise sigmas (``residual_spread``)
    backfacing: int = 0  # pixels where the model's nearest surface faces away from the camera

    @property
    def fitness(self) -> float:
        return self.inliers / max(self.inliers + self.violations, 1)

    @property
    def support(self) -> float:
        return self.inliers / max(self.visible, 1)

    @property
    def facing_share(self) -> float:
        """Share of the model's pixels where its nearest surface faces the camera (1 with none)."""
        total = self.visible + self.backfacing
        return self.visible / total if total else 1.0

    @property
    def clutter(self) -> float:
        """Share of the measured outline where the scene continues the model's surface."""
        return self.outline_continuing / max(self.outline_measured, 1)

    @property
    def penetration(self) -> float:
        """Share of the visible model inside a support (behind the table's plane, hidden by its surface)."""
        return self.inside_support / max(self.visible, 1)

    @property
    def colour_agreement(self) -> float:
        """Share of the colour-judged inlier pixels whose colour is the model's (1 when fewer than
        ``MIN_COLOUR_PIXELS`` could be judged: no colour, or too dark)."""
        return self.colour_agreeing / self.colour_judged if self.colour_judged >= MIN_COLOUR_PIXELS else 1.0

    @property
    def distinct_agreement(self) -> float:
        """Share of the judged pixels where the model's colour is no grey (``colour_distinct``) whose
        colour is the model's: the agreement a grey or white surface cannot give (0 when fewer than
        ``MIN_COLOUR_PIXELS``: no such evidence)."""
        if self.colour_distinct < MIN_COLOUR_PIXELS:
            return 0.0
        return self.colour_distinct_agreeing / self.colour_distinct

    @property
    def flush(self) -> float:
        """Share of the measured outline flush with the model's edge beside it (no depth step), where
        no support is: the model drawn on a surface that goes on, whatever its shape."""
        return self.outline_flush / max(self.outline_measured, 1)

    @property
    def outline_seen(self) -> float:
        """Share of the outline with measured depth (1 when the silhouette has no ring in the image)."""
        return self.outline_measured / self.outline if self.outline else 1.0


def verdict(
    view: DepthView,
    points: np.ndarray,
    normals: np.ndarray,
    camera_T_object: np.ndarray,
    tolerance_m: float,
    noise_per_m2: float,
    planes: np.ndarray | None = None,
    chroma_range: np.ndarray | None = None,
    colour_tolerance: float = 0.1,
    spacing_m: float = 0.01,
    support: np.ndarray | None = None,
    min_saturation: float = 1.0,
) -> Verdict:
    """Judge one hypothesis: model points and outward normals (M, 3, object frame) posed by
    camera_T_object (4, 4). Tolerance at depth z: ``tolerance_m + noise_per_m2 * z^2`` (m).

    planes (P, 4): supports removed from the scene (a x + b y + c z + d = 0, normal towards the
    camera). An occluded model point hidden by a surface on one of them, and itself behind that
    plane by more than ``tolerance_m``, would be inside the support: a pose no object can have.

    chroma_range (M, 4): each model point's colours (``chroma_ranges``), judged against the view's
    colour where both have one: agreeing when its chromaticity is within ``colour_tolerance`` of
    the range in r and in g, the range paled towards grey down to ``min_saturation`` if need be
    (``colour_agrees``). spacing_m: the model points' spacing (m; their voxel), which sets how
    far apart they land in the image and so how much of the silhouette is gaps between them.
    noise_per_m2 is three depth-noise sigmas at 1 m (they grow with z^2): the inliers' residual
    spread (``residual_spread``) is judged in them. support (4,): the plane the object stands on (a,
    b, c, d; unit normal), where its outline meets a surface with no step (``Verdict.flush``)."""
    p, n, front, u, v, ok = _posed(view, points, normals, camera_T_object)
    H, W = view.near.shape
    backfacing = _backfacing(p[ok], u[ok], v[ok], front[ok], W)
    keep = front & ok
    p, u, v = p[keep], u[keep], v[keep]
    seen, flat, z, rows = _seen(p, u, v, W)
    voter = np.flatnonzero(keep)[rows]  # each pixel's point's row in the model
    tol, inlier, violation, occluded = _against(view, flat, z, tolerance_m, noise_per_m2)
    inside = 0
    if planes is not None and len(planes) and occluded.any():
        inside = _inside_support(view, flat[occluded], z[occluded], tol[occluded], planes, tolerance_m)
    gap_px = view.K[0, 0] * spacing_m / float(np.median(z)) if len(z) else 0.0
    outline = _outline(view, u[seen], v[seen], p[seen], n[keep][seen], tolerance_m, noise_per_m2, gap_px, support)
    judged = agreeing = distinct = distinct_agreeing = 0
    if chroma_range is not None and view.chroma is not None:
        scene = view.chroma.reshape(-1, 2)[flat[inlier]]
        lo, hi = chroma_range[voter[inlier], :2], chroma_range[voter[inlier], 2:]
        both = np.all(np.isfinite(scene), axis=1) & np.all(np.isfinite(lo), axis=1)
        judged = int(both.sum())
        with np.errstate(invalid="ignore"):
            agree = colour_agrees(scene, lo, hi, colour_tolerance, min_saturation) & both
            distinct = distinct_from_grey(lo, hi, colour_tolerance) & both
            agreeing, distinct_agreeing, distinct = int(agree.sum()), int((agree & distinct).sum()), int(distinct.sum())
    shape_error = 0.0
    if inlier.sum() >= MIN_SHAPE_PIXELS:
        sigma = noise_per_m2 / 3 * float(np.median(z[inlier])) ** 2  # noise_per_m2 is three sigmas' worth
        spread = residual_spread(view, flat[inlier], z[inlier], tol[inlier])
        shape_error = max(spread - SPREAD_FLOOR_M, 0.0) / max(sigma, 1e-6)
    return Verdict(
        len(flat),
        int(inlier.sum()),
        int(violation.sum()),
        int(occluded.sum()),
        _filled(flat[inlier], W, gap_px),
        *outline,
        inside,
        flat[occluded],
        judged,
        agreeing,
        distinct,
        distinct_agreeing,
        shape_error,
        backfacing,
    )


def inliers_and_violations(
    view: DepthView,
    points: np.ndarray,
    normals: np.ndarray,
    camera_T_object: np.ndarray,
    tolerance_m: float,
    noise_per_m2: float,
) -> tuple[int, int]:
    """``verdict``'s inliers and violations alone (its visible fitness is the one over both): a
    cheap judgement of many poses, or of a pose where only that is asked."""
    p, _, front, u, v, ok = _posed(view, points, normals, camera_T_object)
    keep = front & ok
    _, flat, z, _ = _seen(p[keep], u[keep], v[keep], view.near.shape[1])
    _, inlier, violation, _ = _against(view, flat, z, tolerance_m, noise_per_m2)
    return int(inlier.sum()), int(violation.sum())


def _posed(
    view: DepthView, points: np.ndarray, normals: np.ndarray, camera_T_object: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Model points and normals (M, 3) posed by camera_T_object (4, 4) into the camera frame, which
    of them face the camera at the origin, their pixel columns and rows and which land in the view."""
    R, t = camera_T_object[:3, :3], camera_T_object[:3, 3]
    p, n = points @ R.T + t, normals @ R.T
    front = np.einsum("ij,ij->i", n, p) < 0
    u, v, ok = project(p, view.K, view.near.shape)
    return p, n, front, u, v, ok


def _seen(p: np.ndarray, u: np.ndarray, v: np.ndarray, W: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Of posed model points p (N, 3) facing the camera, at pixel columns u and rows v (N,) of an
    image W wide: the mask of those the model's own nearer surface does not hide (only points near
    its nearest one on a coarse cell are seen), and per pixel they land on its flat index, the
    nearest one's depth (m) and its row in p: one vote per pixel."""
    cell = _cells(u, v, W)
    nearest = np.full(cell.max() + 1 if len(cell) else 0, np.inf)
    np.minimum.at(nearest, cell, p[:, 2])
    seen = p[:, 2] <= nearest[cell] + SELF_OCCLUSION_M
    pix, zs, rows = (v * W + u)[seen], p[seen, 2], np.flatnonzero(seen)
    order = np.lexsort((zs, pix))
    pix, zs, rows = pix[order], zs[order], rows[order]
    first = np.r_[True, pix[1:] != pix[:-1]] if len(pix) else np.zeros(0, bool)
    return seen, pix[first], zs[first], rows[first]


def _against(
    view: DepthView, flat: np.ndarray, z: np.ndarray, tolerance_m: float, noise_per_m2: float
) -> tuple[np.ndarray, ...]:
    """Model depths z (m) at flat pixel indices against the measured surface around them: each
    one's tolerance (m) and the masks of inliers, violations (in front of it) and occluded ones
    (behind it); a pixel with no depth is none of them."""
    near, far = view.near.reshape(-1)[flat], view.far.reshape(-1)[flat]
    tol = tolerance_m + noise_per_m2 * z**2
    with np.errstate(invalid="ignore"):
        inlier = (z >= near - tol) & (z <= far + tol)  # False where no depth (NaN)
        violation = z < near - tol
        occluded = z > far + tol
    return tol, inlier, violation, occluded


def _cells(u: np.ndarray, v: np.ndarray, W: int) -> np.ndarray:
    """The coarse cell (SELF_CELL_PX wide) of each pixel column u and row v (N,) of an image W wide."""
    return (v // SELF_CELL_PX) * (W // SELF_CELL_PX + 1) + u // SELF_CELL_PX


def _backfacing(p: np.ndarray, u: np.ndarray, v: np.ndarray, front: np.ndarray, W: int) -> int:
    """How many pixels (columns u, rows v (N,), image W wide) of posed model points p (N, 3) hold a
    point that faces away (``front`` False) within SELF_OCCLUSION_M of the nearest model point on its
    coarse cell, facing or not: where the camera would see the model's surface from behind."""
    if front.all():
        return 0
    cell = _cells(u, v, W)
    nearest = np.full(cell.max() + 1, np.inf)
    np.minimum.at(nearest, cell, p[:, 2])
    back = ~front & (p[:, 2] <= nearest[cell] + SELF_OCCLUSION_M)
    return len(np.unique((v * W + u)[back]))


def residual_spread(view: DepthView, pixels: np.ndarray, z: np.ndarray, tol: np.ndarray) -> float:
    """How far a posed model's surface departs in shape from the measured one (m): the median
    absolute deviation of the depth residual (model z minus measured, at flat pixel indices
    ``pixels``) once the best affine function of the pixel's column and row is taken out. A small
    pose error shifts and tilts the residual; a wrong shape bends it (a can laid along a box's
    edge: its arc against the box's two faces). Pixels whose residual exceeds their tolerance
    ``tol`` (m) or has no depth (the pixel just past an object's edge, inlier by its neighbourhood)
    are left out; 0 with fewer than 3 left."""
    r = z - view.z.reshape(-1)[pixels]
    ok = np.abs(r) <= tol  # False where the pixel has no depth (NaN)
    if ok.sum() < 3:
        return 0.0
    rows, cols = np.divmod(pixels[ok], view.z.shape[1])
    A = np.stack([np.ones(len(rows)), cols, rows], axis=1).astype(np.float64)
    r = r[ok] - A @ np.linalg.lstsq(A, r[ok], rcond=None)[0]
    return float(np.median(np.abs(r - np.median(r))))


def chroma_ranges(points: np.ndarray, colours: np.ndarray, radius_m: float = COLOUR_RADIUS_M) -> np.ndarray:
    """Each model point's colours: the box [r_min, g_min, r_max, g_max] (M, 4) of the
    chromaticities of the model points (M, 3, m) within radius_m of it, colours (M, 3) rgb 0-1
    (NaN where none of them is bright enough to have one)."""
    chroma = chromaticity(np.asarray(colours, np.float32)).astype(np.float64)
    near = radius_neighbours(points, radius_m)
    starts = near.splits[:-1]  # every point is its own neighbour: no segment is empty
    with np.errstate(invalid="ignore"):
        lo = np.fmin.reduceat(chroma[near.index], starts, axis=0)  # fmin: NaN only where all are
        hi = np.fmax.reduceat(chroma[near.index], starts, axis=0)
    return np.concatenate([lo, hi], axis=1)


def colour_agrees(
    scene: np.ndarray, lo: np.ndarray, hi: np.ndarray, tolerance: float, min_saturation: float = 1.0
) -> np.ndarray:
    """Mask (N,) of scene chromaticities (N, 2) within the tolerance, in r and in g, of the model's
    colour range (lo, hi (N, 2)) as it is, or paled: moved towards grey (1/3, 1/3) to k times its
    distance from it, k down to min_saturation, as far as the scene's own colour asks (its share of
    the range's centre, from grey). A sensor's colours can be paler than a model's (its response, a
    model textured by another camera); a hue cannot turn. Never paled so far that a near-grey
    surface would agree (``palest``): colour stays a second opinion against the unsaturated
    surfaces most of a room is."""
    agree = np.all((scene >= lo - tolerance) & (scene <= hi + tolerance), axis=1)
    if min_saturation >= 1.0:
        return agree
    centre = 0.5 * (lo + hi) - GREY
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.einsum("ij,ij->i", scene - GREY, centre) / np.einsum("ij,ij->i", centre, centre)
    k = np.clip(k, np.maximum(min_saturation, palest(lo, hi, tolerance)), 1.0)[:, None]
    pale = np.isfinite(k[:, 0]) & (k[:, 0] < 1.0)
    agree |= pale & np.all((scene >= paled(lo, k) - tolerance) & (scene <= paled(hi, k) + tolerance), axis=1)
    return agree


def paled(chroma: np.ndarray, k: np.ndarray | float) -> np.ndarray:
    """rg-chromaticities (..., 2) moved towards grey to k times their distance from it."""
    return GREY + k * (chroma - GREY)


def palest(lo: np.ndarray, hi: np.ndarray, tolerance: float) -> np.ndarray:
    """The least k (N,) to which colour ranges (lo, hi (N, 2), rg-chromaticity) may be paled
    (moved towards grey to k times their distance from it) and still keep grey out by two
    tolerances in r or in g, so that a scene colour agreeing with it is a tolerance from grey at
    least (a white wall under warm light is not); inf where the range is that near grey already."""
    margin = np.where(lo > GREY, lo - GREY, np.where(hi < GREY, GREY - hi, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.min(np.where(margin > 0, 2.0 * tolerance / margin, np.inf), axis=1)


def distinct_from_grey(lo: np.ndarray, hi: np.ndarray, tolerance: float) -> np.ndarray:
    """Mask (N,) of model colour ranges (rg-chromaticity, lo and hi (N, 2)) that a grey or white
    surface (chromaticity 1/3, 1/3) falls outside of by more than the tolerance: only there can the
    colour of an unsaturated surface, most of a room, disagree with the model's."""
    return np.any((lo > GREY + tolerance) | (hi < GREY - tolerance), axis=1)


def chromaticity(rgb: np.ndarray) -> np.ndarray:
    """rg-chromaticity (..., 2) of colours rgb (..., 3) in 0-1: r and g over r + g + b, which
    shading and exposure scale alike. NaN where r + g + b is under ``MIN_BRIGHTNESS`` (or NaN)."""
    rgb = np.asarray(rgb)
    total = rgb[..., 0] + rgb[..., 1] + rgb[..., 2]  # a reduction over the 3-wide axis takes three times as long
    out = np.empty(rgb.shape[:-1] + (2,), np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        out[..., 0] = rgb[..., 0] / total
        out[..., 1] = rgb[..., 1] / total
    out[~(total >= MIN_BRIGHTNESS)] = np.nan
    return out


def _inside_support(
    view: DepthView, pixels: np.ndarray, z: np.ndarray, band: np.ndarray, planes: np.ndarray, tolerance_m: float
) -> int:
    """How many hidden model points (flat pixel indices, depths z m) are hidden by a surface on one
    of the planes (P, 4), within ``band`` (m, per point: one pixel's noise), and lie over
    ``tolerance_m`` behind it. The plane and the pose are each fitted to hundreds of points: depth
    noise averages out of both, so their distance is judged without it."""
    rows, cols = np.divmod(pixels, view.z.shape[1])
    ray = _rays(view.K, cols, rows)
    hider = ray * view.z.reshape(-1)[pixels][:, None] @ planes[:, :3].T + planes[:, 3]  # (N, P) signed distances
    hidden = ray * z[:, None] @ planes[:, :3].T + planes[:, 3]
    return int(np.any((np.abs(hider) <= band[:, None]) & (hidden < -tolerance_m), axis=1).sum())


def _rays(K: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Camera-frame rays (N, 3) with z = 1 through pixel columns u and rows v (N,)."""
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(len(u))], axis=1)


def _disc(r: int) -> np.ndarray:
    """A filled disc of radius r pixels, as a structuring element."""
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _filled(pixels: np.ndarray, W: int, gap_px: float) -> np.ndarray:
    """The flat pixel indices (image W wide) closed over the gaps between them, when neighbouring
    model points land ``gap_px`` >= 2 apart: up close a model's points hit one pixel in several, and
    two hypotheses on the same surface would hit different ones (a can posed over a carton shared
    17 % of its pixels with it)."""
    if gap_px < 2 or len(pixels) == 0:
        return pixels
    r = int(np.ceil(gap_px / np.sqrt(2)))
    v, u = np.divmod(pixels, W)
    v0, u0 = max(int(v.min()) - r, 0), max(int(u.min()) - r, 0)
    mask = np.zeros((int(v.max()) + r + 1 - v0, int(u.max()) + r + 1 - u0), np.uint8)
    mask[v - v0, u - u0] = 1
    fv, fu = np.nonzero(cv2.morphologyEx(mask, cv2.MORPH_CLOSE, _disc(r)))
    keep = fu + u0 < W
    return (fv[keep] + v0) * W + fu[keep] + u0


def _outline(
    view: DepthView,
    u: np.ndarray,
    v: np.ndarray,
    p: np.ndarray,
    n: np.ndarray,
    tolerance_m: float,
    noise_per_m2: float,
    gap_px: float = 0.0,
    support: np.ndarray | None = None,
) -> tuple[int, int, int, int]:
    """(ring pixels, measured, continuing, flush) around the silhouette of the seen model points p
    (M, 3, camera frame) with outward normals n, at pixels (u, v): a ring pixel continues when the
    measured surface there lies on the tangent plane of the nearest model point (within the
    tolerance, normals within ``SAME_SURFACE_DEG``): the model's surface would go on past its own
    outline; it is flush when its depth is within the tolerance of that point's and it is not on
    ``support`` (a, b, c, d; unit normal), the plane the object stands on.

    gap_px: how far apart neighbouring model points land (px). Up close they land further apart
    than ``OUTLINE_PX[0]``: the silhouette is closed over such gaps (diagonal ones too) and the
    ring starts half a gap out, else ring pixels fall between the model's own points, on its own
    surface, and read as the surface continuing."""
    if len(u) == 0:
        return 0, 0, 0, 0
    H, W = view.z.shape
    inner = max(OUTLINE_PX[0], int(np.ceil(gap_px / 2)))
    outer = inner + OUTLINE_PX[1] - OUTLINE_PX[0]
    closing = max(2, int(np.ceil(gap_px / np.sqrt(2))))
    # Work in the silhouette's box plus the ring: a hypothesis covers a small part of the frame.
    u0, v0 = max(int(u.min()) - outer - 1, 0), max(int(v.min()) - outer - 1, 0)
    u1, v1 = min(int(u.max()) + outer + 2, W), min(int(v.max()) + outer + 2, H)
    box = (v1 - v0, u1 - u0)
    source = np.ones(box, np.uint8)  # zero at the model's pixels: the distance transform's sources
    source[v - v0, u - u0] = 0
    silhouette = cv2.morphologyEx(1 - source, cv2.MORPH_CLOSE, _disc(closing))  # the gaps between model points filled
    ring = (cv2.dilate(silhouette, _disc(outer)) > 0) & ~(cv2.dilate(silhouette, _disc(inner)) > 0)
    rv, ru = np.nonzero(ring)
    if len(rv) == 0:
        return 0, 0, 0, 0
    plane_n = np.zeros(box + (3,))
    plane_d = np.zeros(box)
    plane_n[v - v0, u - u0] = n
    plane_d[v - v0, u - u0] = np.einsum("ij,ij->i", n, p)
    edge_z = np.zeros(box)
    edge_z[v - v0, u - u0] = p[:, 2]
    _, label = cv2.distanceTransformWithLabels(source, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    order = np.flatnonzero(source.reshape(-1) == 0)  # label k is the k-th source pixel in scan order
    nearest = order[label[rv, ru] - 1]
    normal, offset = plane_n.reshape(-1, 3)[nearest], plane_d.reshape(-1)[nearest]
    gv, gu = rv + v0, ru + u0
    with np.errstate(divide="ignore", invalid="ignore"):  # a plane along the ray continues nowhere
        rays = _rays(view.K, gu, gv)
        z_plane = offset / np.einsum("ij,ij->i", normal, rays)
        z = view.z[gv, gu]
        measured = np.isfinite(z)
        tol = tolerance_m + noise_per_m2 * z**2
        same_plane = np.abs(z - z_plane) <= tol
        same_normal = np.abs(np.einsum("ij,ij->i", _depth_normals(view, gu, gv), normal)) >= np.cos(
            np.radians(SAME_SURFACE_DEG)
        )
        flush = measured & (np.abs(z - edge_z.reshape(-1)[nearest]) <= tol)
        if support is not None:  # where an object stands on its support, no step is expected
            flush &= np.abs(rays * z[:, None] @ support[:3] + support[3]) > tol
    return len(rv), int(measured.sum()), int((measured & same_plane & same_normal).sum()), int(flush.sum())


class Explained:
    """The scene pixels the hypotheses accepted so far explain: a pixel explains one object."""

    def __init__(self, max_shared: float = 0.2) -> None:
        self.max_shared = max_shared
        self.pixels: set[int] = set()

    def support(self, v: Verdict, apart: np.ndarray | None = None) -> float:
        """``v.support`` with the pixels an accepted object explains in front of it left out of what
        it should show: the part of an object a found one hides is no evidence against it. apart:
        flat indices of pixels something else is known to hide (left out too)."""
        hidden = self.pixels.intersection(v.hidden.tolist())
        if apart is not None:
            hidden.update(apart.tolist())
        return v.inliers / max(v.visible - len(hidden), 1)

    def admits(self, v: Verdict) -> bool:
        """Whether at most ``max_shared`` of ``v``'s inlier pixels are already explained (more: it
        competes for the same surface with a better hypothesis and loses)."""
        return len(self.pixels.intersection(v.pixels.tolist())) <= self.max_shared * max(len(v.pixels), 1)

    def competing(self, a: Verdict, b: Verdict) -> bool:
        """Whether two hypotheses compete for the same surface: more than ``max_shared`` of the
        fewer's inlier pixels are the other's too."""
        shared = len(np.intersect1d(a.pixels, b.pixels))
        return shared > self.max_shared * max(min(len(a.pixels), len(b.pixels)), 1)

    def admit(self, v: Verdict) -> bool:
        """Accept ``v`` if it ``admits`` it, its inlier pixels then explained."""
        if not self.admits(v):
            return False
        self.pixels.update(v.pixels.tolist())
        return True


def cluster_labels(view: DepthView, points: np.ndarray, clusters: Sequence[np.ndarray]) -> np.ndarray:
    """Each view pixel's cluster (H * W,), flat: the index in ``clusters`` (index arrays into
    ``points`` (N, 3), camera frame) of a point landing there, -1 where none does."""
    H, W = view.near.shape
    labels = np.full(H * W, -1, np.int64)
    for k, idx in enumerate(clusters):
        u, v, ok = project(points[idx], view.K, (H, W))
        labels[(v * W + u)[ok]] = k
    return labels


def hidden_apart(v: Verdict, labels: np.ndarray) -> np.ndarray:
    """Flat indices of ``v``'s hidden pixels where a cluster stands in front other than those
    holding OWN_CLUSTER_SHARE or more of its inlier pixels: something separate from the surface it
    explains (``cluster_labels``)."""
    ids, counts = np.unique(labels[v.pixels], return_counts=True)
    own = ids[counts >= OWN_CLUSTER_SHARE * max(len(v.pixels), 1)]
    in_front = labels[v.hidden]
    return v.hidden[(in_front >= 0) & ~np.isin(in_front, own)]


def project(p: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel columns, rows (int) of camera-frame points (N, 3), and which fall inside the image."""
    H, W = size
    z = np.where(p[:, 2] > 0, p[:, 2], np.nan)
    with np.errstate(invalid="ignore"):
        u = np.floor(K[0, 0] * p[:, 0] / z + K[0, 2] + 0.5)
        v = np.floor(K[1, 1] * p[:, 1] / z + K[1, 2] + 0.5)
        ok = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    return np.where(ok, u, 0).astype(np.int64), np.where(ok, v, 0).astype(np.int64), ok


def virtual_image(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A list of camera-frame points (N, 3) as ``VIRTUAL_K`` sees it: per pixel the nearest point's
    depth (H, W, m; NaN: no point) and that point's row in ``points`` (H, W; -1: none)."""
    H, W = VIRTUAL_SIZE
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    finite = np.flatnonzero(np.all(np.isfinite(pts), axis=1) & (pts[:, 2] > 0))
    u, v, ok = project(pts[finite], VIRTUAL_K, (H, W))
    rows, pixel, depth = finite[ok], (v * W + u)[ok], pts[finite[ok], 2]
    z = np.full(H * W, np.inf)
    np.minimum.at(z, pixel, depth)
    nearest = np.full(H * W, -1, np.int64)
    on_top = depth == z[pixel]
    nearest[pixel[on_top]] = rows[on_top]
    z[np.isinf(z)] = np.nan
    return z.reshape(H, W), nearest.reshape(H, W)


def fit_intrinsics(grid: np.ndarray, step: int = 4) -> np.ndarray:
    """Pinhole K of an organised cloud (H, W, 3) from its own points: x/z and y/z are affine in the
    pixel column and row (least squares over every ``step``-th row and column: at 4 as good as all
    of them)."""
    H, W = grid.shape[:2]
    sample = grid[::step, ::step]
    vv, uu = np.mgrid[0:H:step, 0:W:step]
    ok = np.all(np.isfinite(sample), axis=2) & (sample[..., 2] > 0)
    if ok.sum() < 10:
        return VIRTUAL_K * np.array([[W / 320], [H / 240], [1.0]])
    a = sample[ok, 0] / sample[ok, 2]
    b = sample[ok, 1] / sample[ok, 2]
    # u = fx * a + cx, v = fy * b + cy
    fx, cx = np.polyfit(a, uu[ok].astype(float), 1)
    fy, cy = np.polyfit(b, vv[ok].astype(float), 1)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _depth_normals(view: DepthView, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit surface normals (N, 3) at pixels (u, v) of the view's depth: the cross product of the
    back-projected differences ``NORMAL_STEP_PX`` either side along the row and the column (NaN at
    the border and next to missing depth)."""
    H, W = view.z.shape
    s = NORMAL_STEP_PX

    def point(uu: np.ndarray, vv: np.ndarray) -> np.ndarray:
        inside = (uu >= 0) & (uu < W) & (vv >= 0) & (vv < H)
        z = np.where(inside, view.z[np.clip(vv, 0, H - 1), np.clip(uu, 0, W - 1)], np.nan)
        return _rays(view.K, uu, vv) * z[:, None]

    n = np.cross(point(u + s, v) - point(u - s, v), point(u, v + s) - point(u, v - s))
    with np.errstate(invalid="ignore", divide="ignore"):
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def _filter3(z: np.ndarray, nearest: bool) -> np.ndarray:
    """3x3 neighbourhood minimum (``nearest``) or maximum of z (H, W), ignoring NaN (NaN where the
    whole neighbourhood is)."""
    fill = np.inf if nearest else -np.inf
    morph = cv2.erode if nearest else cv2.dilate  # min / max filters, exact
    out = morph(
        np.where(np.isnan(z), fill, z), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=fill
    )
    out[np.isinf(out)] = np.nan
    return out
