"""Entry point of ``python -m lamina_host``: the ``lamina`` command."""

from lamina_host.cli import main

raise SystemExit(main())
