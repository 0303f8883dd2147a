"""Stage 1, data: OGBench dataset files and the device dataset with its goal sampler (``dataset``),
the scripted expert (``expert``), on-device collection in MJX (``collect``) and small synthetic
datasets with known distances (``synthetic``)."""
