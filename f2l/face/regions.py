"""Face regions on MediaPipe's 468-point face mesh, and the skin mask they give in an image.

Each region is a closed contour of landmark indices (MediaPipe face-mesh topology; "right"
means the subject's right, which is on the image's left for a face toward the camera). The
skin mask keeps pixels inside the face oval and outside every feature region:

* features: eyes (dilated to cover lashes and lid shadows), eyebrows, lips, nostrils;
* border: a band inside the face oval of ``border_fraction`` × the face height, widened to
  ``hair_fraction`` over the upper forehead (where hair falls), because the mesh's silhouette
  and hairline are the least reliable places of a fit;
* hairline: the part of the border that is only the upper-forehead widening (inside the
  shrunken oval, off the features). It is skin unless hair covers it, and it is where a high sun
  lights the face: ``f2l.face.hair`` keeps those of its pixels whose colour is the skin's.

Rasterisation is exact point-in-polygon on pixel centres (the even-odd test of matplotlib's
``Path.contains_points``, in numpy: :func:`_inside`).
"""

from __future__ import annotations

import numpy as np

FACE_OVAL = (10, 338, 297, 332, 284, 251, 389, 356, 454, 323, 361, 288, 397, 365, 379, 378, 400,
             377, 152, 148, 176, 149, 150, 136, 172, 58, 132, 93, 234, 127, 162, 21, 54, 103, 67,
             109)
LIPS_OUTER = (61, 146, 91, 181, 84, 17, 314, 405, 321, 375, 291, 409, 270, 269, 267, 0, 37, 39,
              40, 185)
RIGHT_EYE = (33, 7, 163, 144, 145, 153, 154, 155, 133, 173, 157, 158, 159, 160, 161, 246)
LEFT_EYE = (263, 249, 390, 373, 374, 380, 381, 382, 362, 398, 384, 385, 386, 387, 388, 466)
RIGHT_BROW = (70, 63, 105, 66, 107, 55, 65, 52, 53, 46)
LEFT_BROW = (300, 293, 334, 296, 336, 285, 295, 282, 283, 276)
# Nostril openings: landmarks around the dark opening under each ala (an unordered set; the
# polygon is their outline ordered by angle about the centroid). Left = mirror indices.
RIGHT_NOSTRIL = (219, 218, 79, 237, 239, 238, 241, 242, 20, 60, 75, 240)
LEFT_NOSTRIL = (439, 438, 309, 457, 459, 458, 461, 462, 250, 290, 305, 460)
IRIS_RIGHT = tuple(range(468, 473))  # centre first, then 4 rim points
IRIS_LEFT = tuple(range(473, 478))

FEATURES = {
    "right_eye": RIGHT_EYE, "left_eye": LEFT_EYE, "right_brow": RIGHT_BROW,
    "left_brow": LEFT_BROW, "lips": LIPS_OUTER, "right_nostril": RIGHT_NOSTRIL,
    "left_nostril": LEFT_NOSTRIL,
}
# Dilation of each feature polygon about its centroid (lashes, lid shadow, brow hair, lip line).
FEATURE_DILATION = {"right_eye": 1.35, "left_eye": 1.35, "right_brow": 1.25, "left_brow": 1.25,
                    "lips": 1.12, "right_nostril": 1.1, "left_nostril": 1.1}
BORDER_FRACTION = 0.05
HAIR_FRACTION = 0.14


def _inside(polygon_xy: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
    """Points (M, 2) inside the closed polygon (K, 2) by the even-odd rule: a ray along +x from
    each point crosses an odd number of edges. The same test, in the same float64 arithmetic, as
    matplotlib's ``Path(polygon).contains_points`` (Haines' crossings-multiply test, its
    ``point_in_path_impl``), so the masks are identical, on edges and vertices too, without
    importing matplotlib (~0.1 s). A polygon of fewer than 3 vertices and a non-finite point
    contain nothing."""
    poly = np.asarray(polygon_xy, dtype=np.float64)
    pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    inside = np.zeros(len(pts), dtype=bool)
    if len(poly) < 3:
        return inside
    # only a point with min y < y <= max y sees an edge's ends on both sides of its ray
    rows = np.nonzero((pts[:, 1] > poly[:, 1].min()) & (pts[:, 1] <= poly[:, 1].max())
                      & np.isfinite(pts).all(axis=1))[0]
    tx, ty = pts[rows, 0], pts[rows, 1]
    odd = np.zeros(len(rows), dtype=bool)
    for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, axis=0)):
        above0, above1 = y0 >= ty, y1 >= ty
        crosses = ((y1 - ty) * (x0 - x1) >= (x1 - tx) * (y0 - y1)) == above1
        odd ^= (above0 != above1) & crosses
    inside[rows] = odd
    return inside


def _dilate(polygon_xy: np.ndarray, factor: float) -> np.ndarray:
    c = polygon_xy.mean(0)
    return c + (polygon_xy - c) * factor


_UNORDERED = ("right_nostril", "left_nostril")


def _by_angle(points: np.ndarray) -> np.ndarray:
    d = points - points.mean(0)
    return points[np.argsort(np.arctan2(d[:, 1], d[:, 0]))]


def feature_polygons(landmarks_xy: np.ndarray) -> dict[str, np.ndarray]:
    """Feature contours (dilated) as (K, 2) arrays in the landmarks' image coordinates."""
    xy = np.asarray(landmarks_xy, dtype=np.float64)[:, :2]
    out = {}
    for name, idx in FEATURES.items():
        poly = xy[list(idx)]
        if name in _UNORDERED:
            poly = _by_angle(poly)
        out[name] = _dilate(poly, FEATURE_DILATION[name])
    return out


def skin_regions(landmarks_xy: np.ndarray, points_xy: np.ndarray, *,
                 border_fraction: float = BORDER_FRACTION,
                 hair_fraction: float = HAIR_FRACTION) -> dict[str, np.ndarray]:
    """Classify image points (M, 2) (x right, y down, same frame as ``landmarks_xy``).

    Returns (M,) bool arrays ``features`` (inside an eye, brow, lip or nostril polygon),
    ``border`` (inside the face oval but within the border/hairline band, or outside the oval)
    and ``skin`` (neither); ``hairline`` is the part of ``border`` that only the hairline band
    excludes (inside the shrunken oval).
    """
    xy = np.asarray(landmarks_xy, dtype=np.float64)[:, :2]
    pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    features = np.zeros(len(pts), dtype=bool)
    for poly in feature_polygons(xy).values():
        features |= _inside(poly, pts)
    oval = xy[list(FACE_OVAL)]
    height = float(np.linalg.norm(xy[10] - xy[152]))  # forehead top to chin
    inner = _shrink_polygon(oval, border_fraction * height)
    outside = ~_inside(inner, pts)
    # hairline band: points above the line through the brows' tops, offset upward
    up = xy[10] - xy[152]
    up /= np.linalg.norm(up)
    forehead = xy[10]
    hair_line = forehead - up * hair_fraction * height
    hairline = ((pts - hair_line) @ up > 0) & ~outside & ~features
    border = (outside | hairline) & ~features
    return {"features": features, "border": border, "hairline": hairline, "skin": ~features & ~border}


def _shrink_polygon(poly: np.ndarray, distance: float) -> np.ndarray:
    """Move each vertex of a closed polygon inward by ``distance`` along its vertex normal
    (the polygon is star-shaped about its centroid, as the face oval is)."""
    prev = np.roll(poly, 1, axis=0)
    nxt = np.roll(poly, -1, axis=0)
    tangent = nxt - prev
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    c = poly.mean(0)
    inward = np.sign(np.einsum("ij,ij->i", c - poly, normal))[:, None]
    return poly + normal * inward * distance
