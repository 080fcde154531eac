"""`python -m sdfr.cli`: the `sdfr` command."""

from sdfr.cli import main

raise SystemExit(main())
