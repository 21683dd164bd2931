"""Filling depth where nothing else gives a value: nearest sparse point, or edge-aware diffusion.

:func:`edge_aware_fill` is a normalised convolution with the fast global smoother (FGS, opencv
``ximgproc``) guided by the image: ``fill = FGS(depth * weight) / FGS(weight)``, run at a reduced
resolution for speed, so values spread along surfaces and stop at colour edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mogs_node.geometry import check_array

__all__ = [
    "PlaneSelect",
    "colour_share_of",
    "complete_planar_masks",
    "consistent_seeds",
    "edge_aware_fill",
    "nearest_fill",
    "smooth_field",
]

F32 = NDArray[np.float32]


def nearest_fill(shape: tuple[int, int], u: NDArray, v: NDArray, depth_m: NDArray) -> F32:
    """Depth of the nearest seed pixel everywhere (``[H, W]`` float32; 0 when there is no seed)."""
    H, W = shape
    out = np.zeros((H, W), np.float32)
    if len(depth_m) == 0:
        return out
    seeds = np.ones((H, W), np.uint8)
    seeds[v, u] = 0
    _, lab = cv2.distanceTransformWithLabels(seeds, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    seed_img = np.zeros((H, W), np.float32)
    seed_img[v, u] = depth_m
    # DIST_LABEL_PIXEL numbers the zero (seed) pixels 1..S in raster order
    vals = seed_img.ravel()[np.flatnonzero(seeds.ravel() == 0)]
    return vals[np.clip(lab - 1, 0, len(vals) - 1)]


def edge_aware_fill(
    depth_m: F32,
    weight: F32,
    guide_rgb: NDArray[np.uint8] | None,
    scale: float = 0.5,
    lam: float = 50.0,
    sigma_color: float = 8.0,
    geometric: bool = False,
) -> F32:
    """Edge-aware normalised-convolution fill of ``depth_m`` ``[H, W]`` from pixels with weight > 0.

    With ``geometric`` the fill averages log depth (a weighted geometric mean: a far seed does
    not dominate a near region as it does in a linear average).
    Returns ``[H, W]`` float32, 0 where no seed reaches (the weight diffused there is ~0).
    """
    H, W = depth_m.shape
    w = np.where(np.isfinite(depth_m) & (depth_m > 0), weight, 0.0).astype(np.float32)
    if not np.any(w > 0):
        return np.zeros((H, W), np.float32)
    d = np.where(w > 0, depth_m, 1.0).astype(np.float32)
    if geometric:
        d = np.log(d)
    d = np.where(w > 0, d, 0.0).astype(np.float32)
    h2, w2 = max(1, round(H * scale)), max(1, round(W * scale))
    if guide_rgb is None:
        guide = np.zeros((h2, w2, 3), np.uint8)
    else:
        guide = cv2.resize(np.ascontiguousarray(guide_rgb), (w2, h2), interpolation=cv2.INTER_AREA)
    ws = cv2.resize(w, (w2, h2), interpolation=cv2.INTER_AREA)
    ds = cv2.resize(d * w, (w2, h2), interpolation=cv2.INTER_AREA)
    num = cv2.ximgproc.fastGlobalSmootherFilter(guide, ds, lam, sigma_color)
    den = cv2.ximgproc.fastGlobalSmootherFilter(guide, ws, lam, sigma_color)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(den > 1e-6 * max(float(ws.max()), 1e-12), num / den, 0.0).astype(np.float32)
    reached = den > 1e-6 * max(float(ws.max()), 1e-12)
    if geometric:
        f = np.where(reached, np.exp(np.clip(f, -80.0, 80.0)), 0.0).astype(np.float32)
    f = cv2.resize(f, (W, H), interpolation=cv2.INTER_LINEAR)
    return np.where(np.isfinite(f) & (f > 0), f, 0.0).astype(np.float32)


def consistent_seeds(
    uv_px: NDArray[np.floating],
    depth_m: NDArray[np.floating],
    k: int = 8,
    gate: float = 0.3,
    radius_px: float = np.inf,
    min_neighbours: int = 2,
) -> NDArray[np.bool_]:
    """Sparse points confirmed by their image neighbours ``[N]`` bool.

    A point is kept when at least ``min_neighbours`` of its ``k`` nearest points lie within
    ``radius_px`` and ``|log z - median(log z of those neighbours)| <= log(1 + gate)``: a gross
    outlier (a mismatched track) disagrees with its neighbours and an isolated point cannot be
    checked, so neither seeds a fill where no prior checks it. A lone point on the near side of a
    depth edge is dropped as well, which costs the fill a little coverage.
    """
    from scipy.spatial import cKDTree

    n = len(depth_m)
    if n <= min_neighbours:
        return np.zeros(n, bool)
    kk = min(k, n - 1)
    dist, nb = cKDTree(uv_px).query(uv_px, kk + 1, distance_upper_bound=radius_px)
    dist, nb = dist[:, 1:], nb[:, 1:]  # drop the point itself
    lz = np.append(np.log(depth_m), np.nan)  # index n: no neighbour within the radius
    near = np.where(np.isfinite(dist), lz[np.minimum(nb, n)], np.nan)
    enough = np.isfinite(near).sum(axis=1) >= min_neighbours
    with np.errstate(invalid="ignore"):
        med = np.nanmedian(np.where(enough[:, None], near, 0.0), axis=1)
    return enough & (np.abs(lz[:n] - med) <= np.log1p(gate))


def smooth_field(
    shape: tuple[int, int],
    flat_idx: NDArray[np.intp],
    values: NDArray[np.floating],
    weight: NDArray[np.floating],
    sigma_frac: float = 0.08,
    scale: float = 0.125,
    clip: float = 0.5,
    exponentiate: bool = False,
    shrink: float = 0.0,
    at: NDArray[np.intp] | None = None,
) -> F32:
    """Low-frequency field ``[H, W]`` float32 from scattered samples (Gaussian normalised conv.).

    ``flat_idx`` ``[N]`` flat pixel indices into ``shape``, ``values`` / ``weight`` ``[N]``.
    Accumulates at ``scale`` resolution (``bincount``), blurs numerator and weight with a Gaussian
    of ``sigma_frac`` times the image width, clips to ``[-clip, clip]`` (0 far from every sample),
    optionally exponentiates (still at low resolution: the field is smooth), and upsamples
    bilinearly. ``shrink`` adds a pseudo-observation of value 0 with the weight of that many
    samples per Gaussian footprint: far from the samples the field decays to 0 instead of
    extrapolating the nearest ones. With ``at`` (flat indices ``[K]``) only the field at those
    pixels is returned ``[K]`` (the value of their low-resolution cell), skipping the upsampling.
    """
    H, W = shape
    h2, w2 = max(1, round(H * scale)), max(1, round(W * scale))
    if len(flat_idx) == 0:
        return np.full(shape if at is None else len(at), 1.0 if exponentiate else 0.0, np.float32)
    v = np.minimum((flat_idx // W) * h2 // H, h2 - 1)
    u = np.minimum((flat_idx % W) * w2 // W, w2 - 1)
    cell = v * w2 + u
    num = np.bincount(cell, weight * values, minlength=h2 * w2).reshape(h2, w2).astype(np.float32)
    den = np.bincount(cell, weight, minlength=h2 * w2).reshape(h2, w2).astype(np.float32)
    sig = max(sigma_frac * w2, 0.5)
    num = cv2.GaussianBlur(num, (0, 0), sig, borderType=cv2.BORDER_REPLICATE)
    den = cv2.GaussianBlur(den, (0, 0), sig, borderType=cv2.BORDER_REPLICATE)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.float32(shrink / (2.0 * np.pi * sig * sig))
        f = np.where(den + k > 1e-12, num / (den + k), 0.0).astype(np.float32)
    f = np.clip(np.nan_to_num(f), -clip, clip)
    if exponentiate:
        f = np.exp(f)
    if at is not None:  # the cell of each pixel: the field varies little within a cell
        return f[np.minimum((at // W) * h2 // H, h2 - 1), np.minimum((at % W) * w2 // W, w2 - 1)]
    return cv2.resize(f, (W, H), interpolation=cv2.INTER_LINEAR)


@dataclass(frozen=True)
class PlaneSelect:
    """Which pixels :func:`complete_planar_masks` fits and which it gives the plane's depth.

    ``prior_conf`` ``[H, W]``: the prior's confidence (None: the output confidence); the plane is
    fitted to pixels with ``prior_conf >= fit_min_conf`` only, and pixels with a depth but
    ``prior_conf < replace_below`` are replaced like holes (0: holes only). Near textureless
    objects (pillars, a bonnet) hold background depth seen through a partial prior at low
    confidence; fitted to the confident pixels only, their plane replaces it (docs/metrizer.md,
    "Whole objects from the confident pixels").
    """

    prior_conf: NDArray[np.float32] | None = None
    fit_min_conf: float = 0.0
    replace_below: float = 0.0
    max_gap_px: float = 0.0  # > 0: only pixels this close to an inlier of their object
    # ... or, farther but within colour_gap_px (> 0), pixels whose colour the object's inliers
    # have (at least colour_share of them in the pixel's colour bin of image_rgb [H, W, 3]
    # uint8): a plane does not cross into a surface of other colours (a bonnet below the
    # background its object was fitted to, the background seen between a tree's leaves)
    colour_gap_px: float = 0.0
    colour_share: float = 0.1
    image_rgb: NDArray[np.uint8] | None = None
    # [H, W] bool: only these pixels are fitted, count for min_share and are inliers a plane
    # reaches from (None: every pixel with a depth). A plane fitted to depth the metrizer itself
    # extrapolated from a few points carries that extrapolation on, across the object's depth
    # jumps (docs/metrizer.md "Planes from measured support only")
    support: NDArray[np.bool_] | None = None


COLOUR_LEVELS = 6  # colour bins per channel of :func:`colour_share_of`


def colour_share_of(
    image_rgb: NDArray[np.uint8],
    reference: tuple[NDArray[np.intp], NDArray[np.intp]],
    query: tuple[NDArray[np.intp], NDArray[np.intp]],
    n_objects: int,
) -> NDArray[np.float64]:
    """For each ``query`` pixel (flat index, object), the share of its object's ``reference``
    pixels (flat index, object) whose colour falls in the query's colour bin (``COLOUR_LEVELS``
    per channel of ``image_rgb`` ``[H, W, 3]`` uint8); 0 for an object without references."""
    rgb = np.asarray(image_rgb).reshape(-1, 3)
    n_bins = COLOUR_LEVELS**3
    q = (rgb.astype(np.intp) * COLOUR_LEVELS) // 256
    bins = (q[:, 0] * COLOUR_LEVELS + q[:, 1]) * COLOUR_LEVELS + q[:, 2]
    (r_idx, r_obj), (q_idx, q_obj) = reference, query
    counts = np.bincount(r_obj * n_bins + bins[r_idx], minlength=n_objects * n_bins)
    n_ref = np.bincount(r_obj, minlength=n_objects)[:n_objects]
    return counts[q_obj * n_bins + bins[q_idx]] / np.maximum(n_ref[q_obj], 1)


def _near_own_inliers(
    inliers: tuple[NDArray[np.intp], NDArray[np.intp]],
    pixels: tuple[NDArray[np.intp], NDArray[np.intp]],
    hw: tuple[int, int],
    max_gap_px: float,
) -> tuple[NDArray[np.bool_], NDArray[np.float32]]:
    """Whether each of ``pixels`` (flat index, object) lies within ``max_gap_px`` of one of the
    ``inliers`` (flat index, object) of its own object: the nearest inlier's object, by one
    labelled distance transform; and the distance to it [px]. A plane is not carried across an
    object to pixels far from what it was fitted to (an under-segmented object: its confident
    pixels on the background)."""
    (in_idx, in_obj), (idx, obj) = inliers, pixels
    H, W = hw
    free = np.ones(H * W, np.uint8)
    free[in_idx] = 0
    dist, lab = cv2.distanceTransformWithLabels(
        free.reshape(H, W), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    # DIST_LABEL_PIXEL numbers the zero pixels 1.. in raster order: map each to its object
    owner = np.full(H * W + 1, -1, np.intp)
    order = np.sort(in_idx)
    pix_obj = np.full(H * W, -1, np.intp)
    pix_obj[in_idx] = in_obj
    owner[1 : len(order) + 1] = pix_obj[order]
    near = owner[lab.ravel()[idx]]
    gap = dist.ravel()[idx]
    return (near == obj) & (gap <= max_gap_px), gap


def _reachable(
    sel: PlaneSelect,
    inliers: tuple[NDArray[np.intp], NDArray[np.intp]],
    pixels: tuple[NDArray[np.intp], NDArray[np.intp]],
    hw: tuple[int, int],
    n_objects: int,
) -> NDArray[np.bool_]:
    """Which ``pixels`` (flat index, object) a plane fitted to ``inliers`` may reach: nearest to
    an inlier of their own object, within ``sel.max_gap_px`` of it, or within
    ``sel.colour_gap_px`` and of a colour the inliers have (:func:`colour_share_of`)."""
    with_colour = sel.colour_gap_px > 0 and sel.image_rgb is not None
    reach = max(sel.max_gap_px, sel.colour_gap_px if with_colour else 0.0)
    own, gap = _near_own_inliers(inliers, pixels, hw, reach)
    far = own & (gap > sel.max_gap_px)
    if far.any():
        img = check_array("image_rgb", sel.image_rgb, shape=(*hw, 3), dtype=np.uint8)
        (idx, obj) = pixels
        share = colour_share_of(img, inliers, (idx[far], obj[far]), n_objects)
        own[far] = share >= sel.colour_share
    return own


def complete_planar_masks(
    depth_m: NDArray[np.float32],
    confidence: NDArray[np.float32],
    objects: NDArray[np.integer],
    n_objects: int,
    *,
    min_share: float = 0.3,
    inlier_rel: float = 0.02,
    min_inlier_share: float = 0.5,
    min_depth_m: float = 5.0,
    max_depth_m: float = 72.0,
    min_pixels: int = 30,
    extrapolation: float = 1.25,
    iterations: int = 4,
    min_out_m: float = 0.0,
    select: PlaneSelect | None = None,
) -> int:
    """Give the uncovered pixels of a well-supported object the depth of its plane (in place).

    A plane seen by a pinhole camera has an inverse depth affine in the pixel coordinates,
    ``1/z = a + b u + c v``. Per object (``objects`` ``[H, W]`` ids ``0..n_objects-1``) that
    plane is fitted by IRLS (Huber weights times ``confidence``) to the object's pixels with a
    depth in ``[min_depth_m, max_depth_m]`` (far / sky pixels excluded). Its pixels without
    depth get the plane's depth when the object is supported (docs/metrizer.md, "Whole masks"):
    at least ``min_pixels`` fitted pixels making ``min_share`` of the object, at least
    ``min_inlier_share`` of them within ``inlier_rel`` of the plane (a mask spanning two
    surfaces fails it), its geometric mean depth at least ``min_depth_m`` (nearer objects are where a
    partial prior lets the background show through) and the filled depth within
    ``[z_min / extrapolation, z_max * extrapolation]`` of the inliers and in
    ``[min_out_m, max_depth_m]``. The filled pixels'
    confidence: half the mean confidence of the object's fitted pixels times its inlier share.
    ``select`` (:class:`PlaneSelect`) fits the plane only to pixels the prior is confident of and
    also replaces the depth of the pixels it is not confident of.
    Returns the number of pixels filled. Vectorised over objects (``bincount`` moments).
    """
    H, W = depth_m.shape
    d = depth_m.ravel()
    cf = confidence.ravel()
    sel = select or PlaneSelect()
    pc = cf if sel.prior_conf is None else np.asarray(sel.prior_conf).ravel()
    hole = d <= 0
    if sel.replace_below > 0:
        hole |= (d <= max_depth_m) & (pc < sel.replace_below)
    hidx = np.flatnonzero(hole)
    if len(hidx) == 0:  # a fully covered frame (a learned prior) costs nothing
        return 0
    obj = np.asarray(objects).ravel().astype(np.intp, copy=False)
    G = int(n_objects)
    has_hole = np.bincount(obj[hidx], minlength=G)[:G] > 0
    n_obj = np.bincount(obj, minlength=G)[:G]
    fit = (d > 0) & (d >= min_depth_m * 0.5) & (d <= max_depth_m)
    if sel.fit_min_conf > 0:
        fit &= pc >= sel.fit_min_conf
    if sel.support is not None:
        fit &= check_array("support", sel.support, shape=(H, W), dtype=np.bool_).ravel()
    idx = np.flatnonzero(fit)
    n_fit = np.bincount(obj[idx], minlength=G)[:G]
    cand = (n_fit >= min_pixels) & (n_fit >= min_share * n_obj) & has_hole
    idx = idx[cand[obj[idx]]]
    if len(idx) == 0:
        return 0
    g = obj[idx]
    u = (idx % W - 0.5 * W) / W
    v = (idx // W - 0.5 * H) / W
    y = 1.0 / d[idx].astype(np.float64)
    w0 = np.maximum(cf[idx].astype(np.float64), 1e-3)
    w = w0.copy()
    coef = np.zeros((G, 3))
    feats = (np.ones_like(u), u, v)
    for _ in range(max(1, iterations)):
        A = np.zeros((G, 3, 3))
        b = np.zeros((G, 3))
        for r in range(3):
            b[:, r] = np.bincount(g, w * feats[r] * y, minlength=G)[:G]
            for c in range(r, 3):
                A[:, r, c] = A[:, c, r] = np.bincount(g, w * feats[r] * feats[c], minlength=G)[:G]
        A[:, range(3), range(3)] += 1e-12
        ok = np.linalg.det(A) > 1e-18
        coef[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
        rel = np.abs(coef[g, 0] + coef[g, 1] * u + coef[g, 2] * v - y) / y
        w = w0 / np.maximum(1.0, rel / inlier_rel)
    inl = rel <= inlier_rel
    n_inl = np.bincount(g, inl, minlength=G)[:G]
    zin = d[idx].astype(np.float64)
    zlo = np.full(G, np.inf)
    zhi = np.zeros(G)
    np.minimum.at(zlo, g[inl], zin[inl])
    np.maximum.at(zhi, g[inl], zin[inl])
    zmed_proxy = np.bincount(g, np.log(zin), minlength=G)[:G] / np.maximum(n_fit, 1)
    share_in = n_inl / np.maximum(n_fit, 1)
    good = cand & ok & (share_in >= min_inlier_share) & (np.exp(zmed_proxy) >= min_depth_m)
    conf_g = 0.5 * share_in * np.bincount(g, cf[idx], minlength=G)[:G] / np.maximum(n_fit, 1)
    hidx = hidx[good[obj[hidx]]]
    if len(hidx) == 0:
        return 0
    hg = obj[hidx]
    inv = (
        coef[hg, 0]
        + coef[hg, 1] * (hidx % W - 0.5 * W) / W
        + coef[hg, 2] * (hidx // W - 0.5 * H) / W
    )
    with np.errstate(divide="ignore"):
        z = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-12), 0.0)
    keep = (z >= zlo[hg] / extrapolation) & (z <= zhi[hg] * extrapolation)
    keep &= (z >= min_out_m) & (z <= max_depth_m) & (z > 0)
    if sel.max_gap_px > 0 or (sel.colour_gap_px > 0 and sel.image_rgb is not None):
        keep &= _reachable(sel, (idx[inl], g[inl]), (hidx, hg), (H, W), G)
    depth_m.ravel()[hidx[keep]] = z[keep].astype(np.float32)
    confidence.ravel()[hidx[keep]] = conf_g[hg[keep]].astype(np.float32)
    return int(keep.sum())
