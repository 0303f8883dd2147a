"""Stage 4, the agent at test time: planning on the graph (``plan``), the AQM agent's budgets,
pruning and replanning (``rules``), the vectorised episode scan (``rollout``) and an agent without
learning for checks (``oracle``)."""
