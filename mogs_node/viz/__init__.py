"""Optional rerun (``rerun-sdk``, the ``viz`` extra) sink: images, masks, depth, trajectory, sparse
points and Gaussian centres, live in a viewer or saved to an ``.rrd`` file.

:mod:`mogs_node.viz.rerun_log` turns messages into rerun archetypes (no bus); :mod:`mogs_node.viz.node`
is the node shell. Importing this package does not import rerun.
"""

__all__ = ["ENTITY_PATHS"]

# Where each kind of data goes in the recording (entity paths).
ENTITY_PATHS = {
    "camera": "world/camera",  # current camera pose (/frontend/odometry), pinhole, live image
    "camera_image": "world/camera/image",
    "trajectory": "world/trajectory",  # odometry positions so far, one line strip
    "keyframe": "world/keyframe",  # latest keyframe pose
    "keyframe_image": "world/keyframe/image",  # its pinhole and image
    "masks": "world/keyframe/image/masks",  # /seg/masks (label + 1, 0 = no mask)
    "prior_depth": "world/keyframe/image/prior_depth",  # /prior/depth
    "depth": "world/keyframe/image/depth",  # /metrizer/depth (metric, back-projected)
    "sparse_points": "world/sparse_points",  # keyframe features, world frame
    "gaussians": "world/gaussians",  # Gaussian centres with their colours (/mapper/gaussians)
    "render": "mapper/render",  # /mapper/render
    "stats": "mapper/stats",  # /mapper/stats scalars: stats/<name>
}
