"""The bake's settings: what to compute and how (plain data, no bpy).

Estimators (``BakeSettings.estimator``, ``--estimator``), named by what they compute:

- ``forward-flux`` (default): every lit caster triangle is cut into sub-triangles traced
  forward exactly through the scene and refined until each image on the receiver is straight
  to half a texel; each sub-triangle's flux is spread over its image by exact texel overlap
  (:mod:`addon.bake.estimators.forward_flux`).  Texel-averaged irradiance, noise-free.
- ``path-points``: every exact specular path at every texel supersample, from the (tuple,
  sample) pairs a cull selects, solved by ``solver``: ``spoly`` (Specular Polynomials, Fan et
  al. 2024; every chain), ``newton`` (MNEE from Path Cuts' seeds; R, T), ``sms`` (Specular
  Manifold Sampling; R, T) or ``curve`` (dimension-reduction MNEE; T)
  (:mod:`addon.bake.estimators.path_points`).
- ``path-seeded``: exact paths at the supersamples by Newton from forward-image seeds
  (two-bounce chains; one-bounce chains run ``path-points`` with ``spoly``)
  (:mod:`addon.bake.estimators.path_seeded`).
- ``photon``: light tracing into the texel histogram (:mod:`addon.bake.estimators.photon`).

``bounces`` is a maximum: ``"auto"`` (default) lets the planner (:mod:`addon.bake.plan`) pick
the chains of up to two bounces whose estimated share of a receiver's caustic energy reaches
``plan_threshold``; 1 or 2 force every chain of up to that many bounces that the materials
allow.

The settings of earlier versions keep working as aliases (:func:`resolve_aliases`):
``method`` (``spoly``/``newton``/``sms``/``curve`` → ``solver``; ``photon`` → ``estimator``),
``one_bounce`` (``flux`` / ``points``) and ``two_bounce`` (``flux`` / ``seeded`` / ``exact``)
choose the estimator of the one- and two-bounce chains.
"""

import math
from dataclasses import asdict, dataclass

ESTIMATORS = ("forward-flux", "path-points", "path-seeded", "photon")
SOLVERS = ("spoly", "newton", "sms", "curve")
SOLVER_CHAINS = {
    "spoly": ("R", "T", "RR", "RT", "TR", "TT"),
    "newton": ("R", "T"),
    "sms": ("R", "T"),
    "curve": ("T",),
}
"""The chains each path-points solver solves; other chains are skipped with a status."""

BOUNCES = ("auto", 1, 2)
DEFAULT_PLAN_THRESHOLD = 0.005

# Legacy names (earlier versions' settings) -> the estimator they ran.
ONE_BOUNCE_ALIASES = {"flux": "forward-flux", "points": "path-points"}
TWO_BOUNCE_ALIASES = {"flux": "forward-flux", "seeded": "path-seeded", "exact": "path-points"}


@dataclass
class BakeSettings:
    resolution: int = 0  # texels per side for every receiver; 0: each receiver's own
    samples: int = 4  # supersamples per texel (an s x s stratified grid, rounded up to a square)
    bounces: object = "auto"  # "auto": the planner picks chains of up to 2 bounces; 1 or 2: force up to that many
    plan_threshold: float = DEFAULT_PLAN_THRESHOLD  # auto: skip chains below this share of a receiver's caustic energy
    estimator: str = "forward-flux"  # see ESTIMATORS
    solver: str = "spoly"  # path-points: see SOLVERS
    seed: int = 0
    jitter: bool = True  # jittered (True) or centred (False) supersamples
    light_samples: int = 1  # > 1: sample light radius / area / sun angle (soft caustics)
    margin: int = 16  # texels of padding over UV seams
    cull: object = "bounds"  # path-points: "bounds": Bernstein position bounds (R, T, RR, RT, TR, TT; cone cull where they
    #                           do not apply); "cone" / True: the cone cull; False: side tests only
    gamma: float = math.inf  # bounds cull: solve a tuple with P = min(gamma Ẽ, 1) (Ẽ in W/m²), weight 1/P; inf: all
    batch_tuples: int = 1 << 18
    band_samples: int = 1 << 20
    step_seconds: float = 0.0  # forward-flux: chunks of casters sized to take about this long (progress steps, Esc); 0: by work
    sun_distance: float = 1e5  # x scene size
    caustics: bool = True  # the specular chains
    direct: bool = False  # also the direct light (chain of length 0; for the units test)
    chains: tuple = ()  # restrict to these chains (empty: all planned)
    threads: int = 0  # 0: Numba's default
    device: str = "numba"  # path-points solver device: "numba", "opencl" or "opencl:N" (see solver.api)
    sms_seeds: int = 16  # solver "sms": random Newton seeds per tuple
    photons: int = 1_000_000  # estimator "photon": photons traced (over all lights and light samples)
    pieces: int = 0  # solver "spoly", two bounces: pieces of the resultant's sign scan (0: the solver's default)
    image_depth: int = 6  # forward-flux / path-seeded: subdivision levels of the caster triangles (4 x 4 first)
    memory_budget: float = 0.0  # bytes the bake's texel arrays may take (0: MEMORY_FRACTION of the free memory)
    method: object = None  # alias: "spoly"/"newton"/"sms"/"curve" set solver (and path-points), "photon" the estimator
    one_bounce: object = None  # alias: estimator of R and T ("flux" / "points"); None: ``estimator``
    two_bounce: object = None  # alias: estimator of RR, RT, TR, TT ("flux" / "seeded" / "exact"); None: ``estimator``

    def as_dict(self):
        d = asdict(self)
        d["chains"] = list(self.chains)
        return d

    def max_bounces(self):
        """The most bounces any chain may have: 2 for "auto"."""
        return 2 if self.bounces == "auto" else int(self.bounces)

    def estimator_for(self, chain):
        """The estimator that bakes ``chain`` (the aliases resolved, see the module doc)."""
        if len(chain) == 1 and self.one_bounce is not None:
            return ONE_BOUNCE_ALIASES[self.one_bounce]
        if len(chain) == 2 and self.two_bounce is not None:
            return TWO_BOUNCE_ALIASES[self.two_bounce]
        if self.estimator == "path-seeded" and len(chain) == 1:
            return "path-points"  # Newton seeding is for two vertices; one-bounce exact paths are cheap
        return self.estimator


def resolve_aliases(settings):
    """Fold the legacy ``method`` into ``estimator`` / ``solver`` (in place; returns ``settings``).

    ``method="photon"`` is the photon estimator; a per-tuple method (``newton``, ``sms``,
    ``curve``, and ``spoly`` when the one-bounce estimator is ``points``) is the path-points
    estimator with that solver.  ``method="spoly"`` alone changes nothing: it was the default,
    whose chains ran the forward-flux estimator."""
    m = settings.method
    if m == "photon":
        settings.estimator = "photon"
    elif m in SOLVERS:
        settings.solver = m
        if m != "spoly":
            settings.estimator = "path-points"
    else:
        return settings  # None, or unknown: check_settings says so
    settings.method = None
    return settings


def check_settings(settings):
    """Raise ValueError (one line) for an unknown name or an out-of-range knob."""
    if settings.method is not None and settings.method not in SOLVERS + ("photon",):
        raise ValueError(f"unknown bake method {settings.method!r}; expected one of {', '.join(SOLVERS + ('photon',))}")
    if settings.estimator not in ESTIMATORS:
        raise ValueError(f"unknown estimator {settings.estimator!r}; expected one of {', '.join(ESTIMATORS)}")
    if settings.solver not in SOLVERS:
        raise ValueError(f"unknown solver {settings.solver!r}; expected one of {', '.join(SOLVERS)}")
    if settings.bounces not in BOUNCES:
        raise ValueError(f"bounces must be 'auto', 1 or 2, got {settings.bounces!r}")
    if not 0.0 <= float(settings.plan_threshold) < 1.0:
        raise ValueError(f"plan_threshold must be in [0, 1), got {settings.plan_threshold}")
    if not 1 <= int(settings.sms_seeds) <= 4096:
        raise ValueError(f"sms_seeds must be in [1, 4096], got {settings.sms_seeds}")
    if int(settings.photons) < 1:
        raise ValueError(f"photons must be at least 1, got {settings.photons}")
    if settings.two_bounce is not None and settings.two_bounce not in TWO_BOUNCE_ALIASES:
        raise ValueError(f"two_bounce must be one of {', '.join(TWO_BOUNCE_ALIASES)}, got {settings.two_bounce!r}")
    if settings.one_bounce is not None and settings.one_bounce not in ONE_BOUNCE_ALIASES:
        raise ValueError(f"one_bounce must be 'points' or 'flux', got {settings.one_bounce!r}")
    if not 0 <= int(settings.image_depth) <= 10:
        raise ValueError(f"image_depth must be in [0, 10], got {settings.image_depth}")
    if not float(settings.memory_budget) >= 0.0:
        raise ValueError(f"memory_budget must be 0 (a share of the free memory) or a number of bytes, got {settings.memory_budget}")
    if settings.pieces and not 1 <= int(settings.pieces) <= 1024:
        raise ValueError(f"pieces must be 0 (the solver's default) or in [1, 1024], got {settings.pieces}")
