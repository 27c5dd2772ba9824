"""``python -m appliance`` runs the ``scan3d`` command line."""

from appliance.cli import main

raise SystemExit(main())
