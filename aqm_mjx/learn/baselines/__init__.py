"""The paper's baselines as registry entries (OGBench's family and SAW), one short module each, on
the shared config, state and update of :mod:`.base`."""
