"""Per-group statistics over flat key arrays, vectorised (one sort, no loop over groups).

Shared by the depth prior (contour fill: a region's median outline depth) and the metrizer (merging,
the held-out shape check, the sky's prior value): neither package imports the other.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["group_medians"]


def group_medians(
    group_of_feat: NDArray[np.intp], z: NDArray[np.floating], n_groups: int
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Count ``[G]`` and median ``[G]`` (NaN for an empty group) of ``z`` ``[N]`` per group.

    ``group_of_feat`` ``[N]``: group of each value, in ``0..n_groups-1``. The median of an even
    count is the mean of the two middle values, as :func:`numpy.median`; a NaN sorts last in its
    group (so it is the median only where it is the middle value).
    """
    counts = np.bincount(group_of_feat, minlength=n_groups)
    med = np.full(n_groups, np.nan)
    if len(z):
        order = np.lexsort((z, group_of_feat))
        zs = z[order]
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        has = counts > 0
        lo = start[has] + (counts[has] - 1) // 2
        hi = start[has] + counts[has] // 2
        med[has] = 0.5 * (zs[lo] + zs[hi])
    return counts, med
