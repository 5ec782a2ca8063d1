"""+opt: refine colours (and optionally opacities) of Gaussians on the reference views.

:mod:`.solver` holds the alternating solve and the cross-view guard; :mod:`.backward`
the analytic gradient of front-to-back compositing that it needs.
"""

from .solver import CROSS_SCALES, ReferenceView, RefineOptions, RefineResult, reference_views, refine

__all__ = ["CROSS_SCALES", "ReferenceView", "RefineOptions", "RefineResult", "reference_views", "refine"]
