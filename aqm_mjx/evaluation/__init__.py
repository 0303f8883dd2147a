"""Stage 5, evaluation: OGBench's protocol as an episode table (``protocol``), its chunked and
sharded run (``evaluate``), the report (``report``) and pictures (``plots``)."""
