"""Image metrics of the map's evaluation (``mapper/image_metrics.py``): PSNR and SSIM."""

from __future__ import annotations

import numpy as np
import pytest

from mogs_node.mapper.image_metrics import psnr_db, ssim


def test_psnr_and_ssim_known_values() -> None:
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (20, 30, 3))
    assert ssim(img, img) == pytest.approx(1.0)
    assert psnr_db(0.9 * img + 0.1, 0.9 * img) == pytest.approx(20.0)
    assert psnr_db(np.full((4, 4, 3), 0.5), np.full((4, 4, 3), 0.6)) == pytest.approx(20.0)
    noisy = np.clip(img + rng.normal(0, 0.2, img.shape), 0, 1)
    assert 0.0 < ssim(noisy, img) < 0.9
    assert psnr_db((img * 255).astype(np.uint8), img) > 40.0
