"""aqm_mjx: Adaptive Quasimetric Mapping for offline goal-conditioned navigation, on device with MJX."""

__version__ = '0.1.0'
