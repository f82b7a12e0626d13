"""Forward estimators of caustic irradiance: forward-traced sub-triangle images, photon tracing."""
