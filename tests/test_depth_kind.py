"""One depth-kind enum and one resampling policy per role (mogs_node.depth_kind)."""

from __future__ import annotations

import numpy as np
import pytest

from mogs_node import msgs
from mogs_node.depth_kind import DEPTH_KINDS, DepthKind, resample_metrized, resample_prior
from mogs_node.depth_prior.depth_anything_onnx import OUTPUT_KINDS
from mogs_node.errors import ConfigError
from mogs_node.metrizer.alignment import PRIOR_KINDS


def test_every_list_of_kinds_is_the_enum_in_one_order() -> None:
    assert DEPTH_KINDS == ("metric", "relative_depth", "relative_inverse_depth")
    assert msgs.DepthMap.KINDS == PRIOR_KINDS == OUTPUT_KINDS == DEPTH_KINDS
    assert DepthKind.RELATIVE_INVERSE_DEPTH == "relative_inverse_depth"  # equal to its string


def test_parse_names_the_place_and_the_choices() -> None:
    assert DepthKind.parse("relative_depth", "prior.kind") is DepthKind.RELATIVE_DEPTH
    with pytest.raises(ConfigError, match=r"prior\.kind: expected one of .*'metric'.*got 'inv'"):
        DepthKind.parse("inv", "prior.kind")


def test_a_prior_is_resampled_bilinearly_and_a_metrized_depth_nearest() -> None:
    d = np.array([[10.0, 20.0], [10.0, 20.0]], np.float32)
    c = np.array([[1.0, 0.0], [1.0, 0.0]], np.float32)
    pd, pc = resample_prior(d, c, 4, 2)
    md, mc = resample_metrized(d, c, 4, 2)
    # bilinear blends the two columns in between; nearest only ever repeats input values
    assert np.allclose(pd[0], [10.0, 12.5, 17.5, 20.0]) and np.allclose(pc[0], [1, 0.75, 0.25, 0])
    assert set(np.unique(md)) <= {10.0, 20.0} and set(np.unique(mc)) <= {0.0, 1.0}
    assert md.shape == mc.shape == pd.shape == (2, 4)


def test_the_same_size_is_returned_untouched() -> None:
    d, c = np.ones((3, 5), np.float32), np.zeros((3, 5), np.float32)
    assert resample_prior(d, c, 5, 3)[0] is d and resample_metrized(d, c, 5, 3)[1] is c
