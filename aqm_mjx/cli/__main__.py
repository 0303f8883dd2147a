"""``python -m aqm_mjx.cli``: the ``aqm-mjx`` command."""

from aqm_mjx.cli import main

raise SystemExit(main())
