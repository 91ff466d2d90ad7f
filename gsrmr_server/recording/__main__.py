"""``python -m gsrmr_server.recording``: see :mod:`gsrmr_server.recording.cli`."""

from gsrmr_server.recording.cli import main

raise SystemExit(main())
