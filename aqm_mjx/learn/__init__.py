"""Stage 2, learning: the quasimetric (``quasimetric``), policies (``policy``) and their objectives
(``objectives``); the contract every method meets (``learner``), AQM (``aqm``) and the method
registry (``methods``); training with checkpoints (``fit``, ``checkpoint``)."""
