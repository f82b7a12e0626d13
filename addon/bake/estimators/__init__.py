"""The bake's estimators of caustic irradiance, one module each, behind the interface of
:mod:`.base` (prepare -> accumulate per band -> flux per receiver -> report):

- :mod:`.forward_flux` ``forward-flux`` (default): forward-traced sub-triangles' flux spread over their images;
- :mod:`.path_points` ``path-points``: exact paths at texel supersamples (solver spoly / newton / sms / curve);
- :mod:`.path_seeded` ``path-seeded``: exact paths at the supersamples by Newton from forward-image seeds;
- :mod:`.photon` ``photon``: light tracing into texel histograms.
"""

from .forward_flux import ForwardFlux
from .path_points import PathPoints
from .path_seeded import PathSeeded
from .photon import Photon

ESTIMATOR_CLASSES = {cls.name: cls for cls in (ForwardFlux, PathPoints, PathSeeded, Photon)}


def make_estimator(name, ctx, items):
    """The estimator called ``name`` (see :data:`addon.bake.settings.ESTIMATORS`) for ``items``."""
    return ESTIMATOR_CLASSES[name](ctx, items)
