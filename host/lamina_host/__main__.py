"""Allow ``python -m lamina_host``."""

from lamina_host.cli import main

raise SystemExit(main())
