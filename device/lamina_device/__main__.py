"""Entry point of ``python -m lamina_device``: the ``lamina-device`` command."""

from lamina_device.cli import main

raise SystemExit(main())
