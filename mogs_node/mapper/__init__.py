"""Gaussian mapper: CPU/CUDA rasterizer, MonoGS-style incremental mapping, PLY output.

See ``docs/mapper.md``. The node shell is :mod:`mogs_node.mapper.node` (imported on its own).
"""

from mogs_node.mapper.mapper import GaussianMapper, MapperParams, export_ply
from mogs_node.mapper.rasterizer import GaussianTensors, RasterParams, RenderOutput, render

__all__ = [
    "GaussianMapper",
    "GaussianTensors",
    "MapperParams",
    "RasterParams",
    "RenderOutput",
    "export_ply",
    "render",
]
