"""Phase (a) of rendering: project Gaussians (EWA) and list their pixel footprints.

- :mod:`.projection`: EWA projection into a camera, culling, footprint boxes, the pose data
  shared by the cameras of one render (:class:`SharedPose`);
- :mod:`.polar`: ERP footprints near a pole, evaluated in the tangent plane of their direction;
- :mod:`.blocks`: the packed ``pixel | depth rank | q`` sort keys and the dense blocks emitting them;
- :mod:`.keys`: the sorted per-pixel front-to-back lists (:func:`footprints`, :func:`sorted_keys`).
"""

from .keys import (
    MAX_CONTRIBUTIONS,
    Footprints,
    KeyJob,
    RenderLimitError,
    footprints,
    job_keys,
    key_job,
    sorted_keys,
)
from .polar import polar_rows
from .projection import (
    ALPHA_MIN,
    LOW_PASS,
    Q_MAX,
    Projected,
    SharedPose,
    gaussian_factors,
    grid_keep,
    opacity_cuts,
    project,
    shared_pose,
    sigma_cuts,
)

__all__ = ["ALPHA_MIN", "LOW_PASS", "MAX_CONTRIBUTIONS", "Q_MAX", "Footprints", "KeyJob", "Projected",
           "RenderLimitError", "SharedPose", "footprints", "gaussian_factors", "grid_keep", "job_keys", "key_job",
           "opacity_cuts", "polar_rows", "project", "shared_pose", "sigma_cuts", "sorted_keys"]
