"""Depth metrizer: multi-scale shape consensus (MSC, paper III-B) and cross-object depth
refinement (CDR, paper III-C). See docs/metrizer.md.

Pure algorithm modules (arrays in, arrays out); ``node.py`` is the only one touching the bus.
"""

from mogs_node.metrizer.pipeline import (
    MODES,
    MetrizedDepth,
    MetrizerInputs,
    MetrizerParams,
    metrize,
    metrize_depth,
)

__all__ = ["MODES", "MetrizedDepth", "MetrizerInputs", "MetrizerParams", "metrize", "metrize_depth"]
