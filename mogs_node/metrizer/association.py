"""Label preparation, feature-to-mask association and region adjacency (paper III-B, first step).

- :func:`prepare_labels`: compact the instance labels to ``0..M-1``; pixels outside every mask
  (``-1``) are split into 4-connected components that become objects of their own (so that sky,
  unsegmented road etc. are handled by the same machinery, and every pixel has an object).
- :func:`associate_features`: a feature belongs to the mask under its rounded pixel; on a mask
  border (the ``(2r+1)^2`` neighbourhood holds more than one label) the neighbourhood votes, ties
  going to the centre pixel's label.
- :func:`region_adjacency`: 4-neighbour pixel pairs across object borders, vectorised.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["associate_features", "boundary_pairs", "prepare_labels", "region_adjacency"]

I32 = NDArray[np.int32]


def prepare_labels(labels: NDArray[np.integer]) -> tuple[I32, int, NDArray[np.bool_]]:
    """Compact ``labels`` ``[H, W]`` (-1 = no mask) to objects ``0..M-1`` covering every pixel.

    Returns ``(obj [H, W] int32, M, unmasked [M] bool)``; ``unmasked[k]`` is True for objects made
    from connected components of ``-1`` pixels. Uses a look-up table (``bincount``), not ``unique``.
    """
    lab = np.asarray(labels)
    mn = int(lab.min()) if lab.size else 0
    mx = int(lab.max()) if lab.size else -1
    if mx > 4 * lab.size + 1024 or mx >= 2**31 - 1:
        # sparse ids (e.g. hashed instance ids): compact by sorting (rare; no huge table)
        neg = lab < 0
        _, inv = np.unique(np.where(neg, -1, lab), return_inverse=True)
        lab = inv.reshape(lab.shape).astype(np.int32) - (1 if neg.any() else 0)
        mn = int(lab.min())
        mx = int(lab.max())
    if mn < -1:
        lab = np.where(lab < 0, -1, lab)
        mx = max(mx, -1)
    lab = lab.astype(np.int32, copy=False)
    flat = lab.ravel()
    masked = None if mn >= 0 else flat >= 0
    if mx >= 0:
        # labels present = labels of the last pixel of every raster run (cheaper than bincount)
        ends = np.flatnonzero(flat[1:] != flat[:-1])
        run_labels = np.concatenate([flat[ends], flat[-1:]])
        present = np.zeros(mx + 1, bool)
        present[run_labels[run_labels >= 0]] = True
    else:
        present = np.zeros(0, bool)
    n_masked = int(present.sum())
    if masked is None and present.all():
        obj = flat.astype(np.int32, copy=True)
    else:
        lut = np.full(mx + 2, -1, np.int32)  # index 0 <- label -1
        lut[1:][present] = np.arange(n_masked, dtype=np.int32)
        obj = lut[flat + 1]
    n_cc = 0
    if masked is not None:
        unm = ~masked.reshape(lab.shape)
        n, cc = cv2.connectedComponents(unm.astype(np.uint8), connectivity=4)
        n_cc = n - 1
        obj[~masked] = cc.ravel()[~masked] - 1 + n_masked
    unmasked = np.zeros(n_masked + n_cc, bool)
    unmasked[n_masked:] = True
    return obj.reshape(lab.shape), n_masked + n_cc, unmasked


def associate_features(obj: I32, uv_px: NDArray[np.floating], radius: int = 1) -> I32:
    """Object id per feature ``[N]`` (-1 when outside the image), with a border vote.

    ``obj`` ``[H, W]`` int32 from :func:`prepare_labels`; ``uv_px`` ``[N, 2]`` finite pixels.
    """
    H, W = obj.shape
    n = len(uv_px)
    out = np.full(n, -1, np.int32)
    if n == 0:
        return out
    u = np.round(uv_px[:, 0]).astype(np.int64)
    v = np.round(uv_px[:, 1]).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    u, v = u[inside], v[inside]
    centre = obj[v, u]
    if radius <= 0:
        out[inside] = centre
        return out
    d = np.arange(-radius, radius + 1)
    du, dv = np.meshgrid(d, d)
    uu = np.clip(u[:, None] + du.ravel()[None], 0, W - 1)
    vv = np.clip(v[:, None] + dv.ravel()[None], 0, H - 1)
    nb = obj[vv, uu]  # [n, (2r+1)^2]
    border = (nb != centre[:, None]).any(axis=1)
    res = centre.copy()
    if border.any():
        nbb, cb = nb[border], centre[border]
        counts = (nbb[:, :, None] == nbb[:, None, :]).sum(axis=2) + 0.5 * (nbb == cb[:, None])
        res[border] = nbb[np.arange(len(nbb)), np.argmax(counts, axis=1)]
    out[inside] = res
    return out


def boundary_pairs(obj: I32) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Flat indices ``(p, q)`` of every 4-neighbour pixel pair whose objects differ."""
    H, W = obj.shape
    # horizontal pairs: index i in the [H, W-1] difference grid is pixel i + i // (W - 1)
    ih = np.flatnonzero(obj[:, :-1] != obj[:, 1:]) if W > 1 else np.zeros(0, np.intp)
    ph = ih + ih // max(W - 1, 1)
    # vertical pairs: index i in the [H-1, W] difference grid is pixel i itself
    pv = np.flatnonzero(obj[:-1, :] != obj[1:, :])
    p = np.concatenate([ph, pv])
    q = np.concatenate([ph + 1, pv + W])
    return p, q


def region_adjacency(
    obj: I32, n_obj: int, pairs: tuple[NDArray[np.intp], NDArray[np.intp]] | None = None
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.int64]]:
    """Adjacent object pairs ``(k, l)`` with ``k < l`` and their border length in pixel pairs."""
    p, q = boundary_pairs(obj) if pairs is None else pairs
    flat = obj.ravel()
    a, b = flat[p].astype(np.int64), flat[q].astype(np.int64)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo * n_obj + hi
    if n_obj * n_obj <= 4_000_000:  # bincount beats sorting for the usual few hundred objects
        cnt = np.bincount(key, minlength=n_obj * n_obj)
        keys = np.flatnonzero(cnt)
        counts = cnt[keys]
    else:
        keys, counts = np.unique(key, return_counts=True)
    return (keys // n_obj).astype(np.intp), (keys % n_obj).astype(np.intp), counts
