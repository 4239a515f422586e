"""Allow ``python -m lamina_device``."""

from lamina_device.cli import main

raise SystemExit(main())
